#!/usr/bin/env python3
"""Fails when a Rust source file is over 900 lines or a function outside tests is over 100.

Functions are found by brace matching from each `fn` item line; `#[cfg(test)]` modules,
`tests/` folders and `#[test]` functions are skipped.
"""
import pathlib
import re
import sys

FILE_LIMIT, FN_LIMIT = 900, 100
FN = re.compile(r"^\s*(pub(\([^)]*\))?\s+)?(const\s+)?(async\s+)?(unsafe\s+)?fn\s+(\w+)")


def body_end(lines, start):
    """Index of the line closing the item that opens on or after `start`."""
    depth, opened = 0, False
    for i in range(start, len(lines)):
        code = re.sub(r'//.*|"(\\.|[^"\\])*"|\'(\\.|[^\'\\])\'', "", lines[i])
        for ch in code:
            if ch == "{":
                depth, opened = depth + 1, True
            elif ch == "}":
                depth -= 1
                if opened and depth == 0:
                    return i
        if not opened and code.rstrip().endswith(";"):
            return i
    return len(lines) - 1


def check(path):
    lines = path.read_text().split("\n")
    problems = []
    if len(lines) - 1 > FILE_LIMIT:
        problems.append(f"{path}: {len(lines) - 1} lines (limit {FILE_LIMIT})")
    i = 0
    while i < len(lines):
        line = lines[i]
        if re.match(r"^\s*#\[cfg\(test\)\]", line):
            i = body_end(lines, i + 1) + 1
            continue
        if re.match(r"^\s*#\[test\]", line):
            i = body_end(lines, i + 1) + 1
            continue
        m = FN.match(line)
        if m:
            end = body_end(lines, i)
            n = end - i + 1
            if n > FN_LIMIT:
                problems.append(f"{path}:{i + 1}: fn {m.group(6)} is {n} lines (limit {FN_LIMIT})")
            # Nested fns are counted as part of their parent only.
            i = end + 1
            continue
        i += 1
    return problems


def main():
    root = pathlib.Path(__file__).resolve().parent.parent
    files = [p for d in ("src", "crates") for p in (root / d).rglob("*.rs")]
    files = [p for p in files if "/tests/" not in str(p.relative_to(root)) and "target" not in p.parts]
    problems = [q for p in sorted(files) for q in check(p)]
    print("\n".join(problems) or "size limits: every file and function within bounds")
    sys.exit(1 if problems else 0)


if __name__ == "__main__":
    main()
