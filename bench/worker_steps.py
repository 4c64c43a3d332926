#!/usr/bin/env python3
"""Each step's gradients and all-reduce time of an `osrt train` run's workers, from their
debug log (`RUST_LOG=osrt_worker=debug`: one line per worker and step with `gradients_s`
and `reduce_s`).

Per step, the worker that reached the all-reduce last waited for no one: its `reduce_s`
is the all-reduce itself (with a GPU worker's staging of the gradient); the other's
includes its wait for the slower one. Prints the medians over the steps after the first
`--skip` (warm-up), and the all-reduce's share of that worker's step.

    python3 bench/worker_steps.py LOG [--skip 2]
"""
import argparse
import re
import statistics
import sys

LINE = re.compile(r"step's gradients and all-reduce step=(\d+) gradients_s=([0-9.e+-]+) reduce_s=([0-9.e+-]+)")


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("log")
    p.add_argument("--skip", type=int, default=2, help="first steps left out (warm-up)")
    a = p.parse_args()
    steps = {}
    with open(a.log, errors="replace") as f:
        for line in f:
            m = LINE.search(line)
            if m:
                steps.setdefault(int(m[1]), []).append((float(m[2]), float(m[3])))
    rows = []
    for step in sorted(steps):
        if step < a.skip:
            continue
        # The last to arrive: the longest gradients.
        g, r = max(steps[step])
        rows.append((step, len(steps[step]), g, r))
    if not rows:
        sys.exit(f"{a.log}: no step lines after step {a.skip} (was RUST_LOG=osrt_worker=debug set?)")
    for step, workers, g, r in rows:
        print(f"step {step:>3} ({workers} workers): last to arrive: gradients {g * 1e3:8.1f} ms, all-reduce {r * 1e3:8.1f} ms")
    g = statistics.median(x[2] for x in rows)
    r = statistics.median(x[3] for x in rows)
    share = statistics.median(x[3] / (x[2] + x[3]) for x in rows)
    print(f"median over {len(rows)} steps: gradients {g * 1e3:.1f} ms, all-reduce {r * 1e3:.1f} ms, "
          f"all-reduce share of the step {100 * share:.1f} %")


if __name__ == "__main__":
    main()
