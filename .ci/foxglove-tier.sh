#!/usr/bin/env bash
# The Foxglove tier: bsc's logs read by a reader the project did not write. Foxglove's MCAP
# library for Node (@mcap/core) reads a recorded session, a replay's output and the odd records
# (health with rejections, alerts, frames without a channel); every schema must be one Foxglove's
# JSON-schema loader takes and every message must validate against it (tests/system/foxglove).
# .ci/run runs it after the main suite. Needs node and npm (the npm registry for `npm ci`, about
# 5 s); without them it fails and says so, it never skips.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || { echo "foxglove-tier: no .venv; run .ci/run (or the README's test command) first" >&2; exit 2; }
if ! command -v node >/dev/null || ! command -v npm >/dev/null; then
  echo "foxglove-tier: needs node and npm (Node 18 or later; e.g. apt-get install nodejs npm): the Foxglove tests did not run" >&2
  exit 1
fi
npm ci --prefix tests/system/foxglove --no-audit --no-fund --loglevel=error
# BSC_FOXGLOVE_TIER: the tests fail instead of skipping when their packages are missing
BSC_FOXGLOVE_TIER=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python -m pytest -q -p no:cacheprovider -m foxglove tests/system/foxglove
