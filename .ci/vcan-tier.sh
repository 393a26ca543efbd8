#!/usr/bin/env bash
# The SocketCAN tier: `pytest -m vcan` inside a VM whose kernel has vcan (see .ci/vcan-vm.sh),
# with one vcan per bus of the paper robot: arm0 -> vcan0, arm1 -> vcan1, spacecraft -> vcan2.
#
#   .ci/vcan-tier.sh [PYTEST ARGS...]        e.g. .ci/vcan-tier.sh -x tests/vcan
#
# Uses the venv the main job made (.ci/run or the README's test command). Python runs about 14x
# slower under QEMU's TCG, so the vcan tests send seconds of traffic, not minutes; the VM limit
# (BSC_VM_TIMEOUT, default 900 s) only turns a hang into a failure. pytest's exit 5 (nothing
# collected, e.g. the vcan marker lost) fails the tier like any other non-zero status.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || { echo "vcan-tier: no .venv; run .ci/run (or the README's test command) first" >&2; exit 2; }
export OPENBLAS_NUM_THREADS=1 PYTHONDONTWRITEBYTECODE=1
export BSC_VM_VCANS=${BSC_VM_VCANS:-3} BSC_VM_TIMEOUT=${BSC_VM_TIMEOUT:-900}
# -p no:cacheprovider: the guest would write .pytest_cache into the host tree as root
exec .ci/vcan-vm.sh .venv/bin/python -m pytest -q -m vcan -p no:cacheprovider "$@"
