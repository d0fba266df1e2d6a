#!/usr/bin/env bash
# The README's test command: set up (idempotent), then run the default test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# Lint and types before the tests, so a finding fails the command (seconds: both keep their caches in .venv).
# The repository root is the package `procam`; mypy finds it through a link, whatever the clone is called.
mkdir -p .venv/mypy-path && ln -sfn ../.. .venv/mypy-path/procam
.venv/bin/ruff check --quiet .
.venv/bin/mypy
# Two test processes, each taking whole files (a module's fixtures are made once; the session's are shared,
# tests/conftest.py): one process alone leaves a third of 2 cores idle in real-time waits and single-threaded
# numpy. `-n 0` after the command runs them in this process; the 15 slowest tests at the end of every run.
exec .venv/bin/python -m pytest -q -p no:cacheprovider --durations=15 -n 2 --dist loadfile "$@"
