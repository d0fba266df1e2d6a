"""The bad-input property suite at length: many more generated cases, fresh random draws, and the table of figures.

    .venv/bin/python scripts/bench_bad_input.py [--scale 10] [-k FORMAT_TEST] [--json FILE]

Runs ``tests/test_bad_input.py`` with ``PROCAM_BAD_INPUT_SCALE`` (each format's number of cases in the default
suite times ``--scale``; about 190 cases at 1) and prints, per format, the cases run, the exit codes seen, and
the internal errors (exit 1), hangs, escapes (a file opened outside the folders the command was given) and losses
(an input or a user's file deleted or changed), then every case that broke a promise, each with what was damaged.
The promise of issue 37 is zero escapes, zero losses and zero internal errors on inputs the user can fix.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", type=float, default=10.0, help="cases per format, times the default suite's")
    parser.add_argument("-k", default="", help="pytest -k selection of the formats' tests (default all)")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args()
    figures = args.json or Path(tempfile.mkdtemp(prefix="bench-bad-input-")) / "figures.json"
    env = {**os.environ, "PROCAM_BAD_INPUT_SCALE": str(args.scale), "PROCAM_BAD_INPUT_RANDOM": "1",
           "PROCAM_BAD_INPUT_FIGURES": str(figures)}
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(REPO / "tests" / "test_bad_input.py")]
    if args.k:
        cmd += ["-k", args.k]
    start = time.monotonic()
    done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    seconds = time.monotonic() - start
    if not figures.is_file():
        print(done.stdout[-3000:], done.stderr[-3000:], sep="\n")
        print("no figures were written: the suite did not run", file=sys.stderr)
        return 1
    doc = json.loads(figures.read_text())
    print(_table(doc))
    cases = sum(doc["cases"].values())
    print(f"\n{cases} cases in {seconds:.0f} s; escapes {sum(doc['escapes'].values())}, losses "
          f"{sum(doc['losses'].values())}, internal errors {sum(doc['internal'].values())}, hangs "
          f"{sum(doc['hangs'].values())}")
    for fmt, failures in sorted(doc["failures"].items()):
        print(f"\n{fmt}: {len(failures)} case(s) broke a promise")
        for line in failures:
            print("  " + line[:400])
    return 0 if done.returncode == 0 else 3


def _table(doc: dict) -> str:
    lines = [f"{'format':<14}{'cases':>6}{'internal':>9}{'hangs':>6}{'escapes':>8}{'losses':>7}  exit codes"]
    for fmt in sorted(doc["cases"]):
        codes = ", ".join(f"{k}: {v}" for k, v in sorted(doc["codes"][fmt].items()))
        lines.append(f"{fmt:<14}{doc['cases'][fmt]:>6}{doc['internal'].get(fmt, 0):>9}{doc['hangs'].get(fmt, 0):>6}"
                     f"{doc['escapes'].get(fmt, 0):>8}{doc['losses'].get(fmt, 0):>7}  {codes}")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
