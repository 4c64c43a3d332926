#!/usr/bin/env python3
"""The GPU time of each kernel of an `osrt bench model` run under Nsight Compute, summed
by kernel name: which of candle's and osrt's kernels a step spends its time in (the
per-op profile of `--profile` stops at op kinds; inside an MLP or attention node it
cannot tell a product from a copy or a cast).

    ncu --clock-control none --cache-control none --metrics gpu__time_duration.sum \
        --csv --page details --log-file ncu.csv osrt bench model --device cuda …
    python3 bench/ncu_kernels.py ncu.csv --steps 3 [--top 40]

Reads ncu's CSV (the `details` page: one row per kernel and metric; or the `raw` page:
one row per kernel with a units row under the header). Durations are per kernel with
the launches serialised, so their sum is the step's kernel time, not its wall time.
"""
import argparse
import csv
import io
import sys

METRIC = "gpu__time_duration.sum"
UNIT_S = {"nsecond": 1e-9, "ns": 1e-9, "usecond": 1e-6, "us": 1e-6, "msecond": 1e-3, "ms": 1e-3,
          "second": 1.0, "s": 1.0}


def number(text):
    return float(text.replace(",", "").strip())


def short(name):
    """A kernel's name without its argument list (templates kept: a GEMM's tile shape is
    in them), as a group key."""
    depth = 0
    for i, c in enumerate(name):
        if c == "<":
            depth += 1
        elif c == ">":
            depth -= 1
        elif c == "(" and depth == 0 and i > 0:
            name = name[:i]
            break
    return name.replace("void ", "", 1).strip()


def durations(text):
    """(kernel name, seconds) for each profiled launch in ncu's CSV output."""
    # ncu prefixes its own messages (==PROF==, ==WARNING==) to the log: the CSV starts at
    # the first line that begins with a quoted field.
    lines = text.splitlines()
    start = next((i for i, l in enumerate(lines) if l.startswith('"')), None)
    if start is None:
        return []
    rows = list(csv.reader(io.StringIO("\n".join(lines[start:]))))
    head, body = rows[0], rows[1:]
    col = {h: i for i, h in enumerate(head)}
    out = []
    if "Metric Name" in col:
        for r in body:
            if len(r) == len(head) and r[col["Metric Name"]] == METRIC:
                unit = UNIT_S.get(r[col["Metric Unit"]].strip(), None)
                if unit is None:
                    sys.exit(f"unknown unit {r[col['Metric Unit']]!r}")
                out.append((r[col["Kernel Name"]], number(r[col["Metric Value"]]) * unit))
    elif METRIC in col:
        units = body[0]
        unit = UNIT_S.get(units[col[METRIC]].strip())
        if unit is None:
            sys.exit(f"unknown unit {units[col[METRIC]]!r}")
        for r in body[1:]:
            if len(r) == len(head):
                out.append((r[col["Kernel Name"]], number(r[col[METRIC]]) * unit))
    else:
        sys.exit(f"no {METRIC} column or rows in the CSV (header: {head[:12]})")
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("csv")
    p.add_argument("--steps", type=int, default=1, help="steps the run profiled (totals are divided by it)")
    p.add_argument("--top", type=int, default=40)
    a = p.parse_args()
    with open(a.csv, errors="replace") as f:
        launches = durations(f.read())
    if not launches:
        sys.exit(f"{a.csv}: no kernel durations (did ncu run?)")
    groups = {}
    for name, s in launches:
        n, t = groups.get(short(name), (0, 0.0))
        groups[short(name)] = (n + 1, t + s)
    total = sum(t for _, t in groups.values())
    print(f"{len(launches)} launches, {total * 1e3 / a.steps:.2f} ms of kernel time a step "
          f"(over {a.steps} step(s) profiled)")
    print(f"{'ms/step':>9} {'share':>6} {'calls/step':>10}  kernel")
    for name, (n, t) in sorted(groups.items(), key=lambda kv: -kv[1][1])[: a.top]:
        print(f"{t * 1e3 / a.steps:9.2f} {100 * t / total:5.1f}% {n / a.steps:10.1f}  {name[:110]}")


if __name__ == "__main__":
    main()
