#!/usr/bin/env bash
# The README's main command: set up (idempotent), then run the built-in demo end to end.
# Extra arguments go to `procam demo` (e.g. --full for full resolution, --out DIR).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/procam demo "$@"
