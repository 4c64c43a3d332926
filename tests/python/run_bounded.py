"""Runs a command with a wall-clock limit and reports, as JSON, how it ended: its exit
code (or the signal that ended it), its seconds, its peak resident memory (the kernel's
ru_maxrss of the waited child) and the tail of its stderr. The limit kills it (SIGKILL)
and says so; nothing else is limited, so the figures are what it took.

    python3 run_bounded.py SECONDS -- COMMAND [ARG ...]
"""
import json
import resource
import subprocess
import sys
import time

limit = float(sys.argv[1])
assert sys.argv[2] == "--", "usage: run_bounded.py SECONDS -- COMMAND [ARG ...]"
start = time.monotonic()
proc = subprocess.Popen(sys.argv[3:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
timed_out = False
try:
    _, err = proc.communicate(timeout=limit)
except subprocess.TimeoutExpired:
    timed_out = True
    proc.kill()
    _, err = proc.communicate()
seconds = time.monotonic() - start
code = proc.returncode
print(json.dumps({
    "code": code if code >= 0 else None,
    "signal": -code if code < 0 else None,
    "timed_out": timed_out,
    "seconds": round(seconds, 3),
    # Linux reports kilobytes.
    "max_rss_bytes": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024,
    "stderr": err.decode("utf-8", "replace")[-4000:],
}))
