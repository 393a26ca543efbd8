#!/usr/bin/env bash
# Runs a command beside two CPU-bound processes, as on a busy two-core machine, and exits with
# the command's status. The test suite must pass like this (tests wait on conditions with
# deadlines, never on sleeps or on "enough messages arrived"):
#
#   OPENBLAS_NUM_THREADS=1 .ci/under-load.sh .venv/bin/python -m pytest -q
set -uo pipefail
[ $# -gt 0 ] || { echo "usage: $0 COMMAND [ARG...]" >&2; exit 2; }
hogs=()
for _ in 1 2; do
  python3 -c 'while True: pass' &
  hogs+=($!)
done
trap 'kill "${hogs[@]}" 2>/dev/null' EXIT
"$@"
