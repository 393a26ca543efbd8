#!/usr/bin/env bash
# The SocketCAN tier: the tests marked `vcan` run inside a VM whose kernel has vcan
# (.ci/vcan-vm.sh), with one vcan per bus: vcan0..vcan3 (the paper robot uses three: arm0, arm1,
# spacecraft; three_arm four). .ci/run runs it after the main suite.
#
#   .ci/vcan-tier.sh [PYTEST OPTIONS...]             every test marked vcan, e.g. -x --durations=0
#   .ci/vcan-tier.sh [PYTEST OPTIONS...] PATH...     only those files/dirs/node ids, e.g. -x tests/system/vcan
#
# Uses the venv the main job made (.ci/run or the README's test command). Python runs about
# 14x slower under QEMU's TCG (interpreter start and imports ~20x), so:
# - the tests are collected on the host (seconds) and only the files holding vcan tests go to
#   the VM; collecting the whole suite there costs over a minute (scipy, assertion rewriting);
# - the vcan tests send short streams and wait for conditions, never for fixed times.
# Limits: BSC_VM_BOOT_TIMEOUT (default 120 s) until the guest runs pytest, BSC_VM_TIMEOUT
# (default 900 s) for the whole VM; both fail the tier (exit 125 / 124), they never hang it.
# pytest's exit 5 (nothing collected, e.g. the vcan marker lost) fails the tier like any other
# non-zero status.
#
# Skipped (exit 0, one "SKIPPED" line on stderr) only where this host cannot run QEMU at all:
# no qemu-system-x86_64 and no way to install it (not root, or no apt-get). KVM is not needed
# (TCG). Everything else (image build, kernel download, boot, a test) fails the tier.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || { echo "vcan-tier: no .venv; run .ci/run (or the README's test command) first" >&2; exit 2; }
if ! command -v qemu-system-x86_64 >/dev/null && { [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; }; then
  echo "vcan-tier: SKIPPED: no qemu-system-x86_64 here and no way to install it (needs root and apt-get);" \
       "the SocketCAN tests did not run" >&2
  exit 0
fi
# Bytecode for the VM, compiled here on the host: the guest must not write the tree (it would
# as root), and compiling the project's modules under TCG costs seconds in every Python process
# the tests start. pytest's rewritten test modules come from the host collection below.
env -u PYTHONDONTWRITEBYTECODE .venv/bin/python -m compileall -q -j 0 -x '/\.' . >/dev/null 2>&1 || true
# The numba kernels, compiled here for a generic x86-64 CPU into a cache the guest reads (the
# guest inherits this environment): compiling them under TCG would take about a quarter of an
# hour, and a cache made for this host's CPU does not load on the VM's.
export NUMBA_CPU_NAME=generic NUMBA_CACHE_DIR="$PWD/.numba-vm"
.venv/bin/python -m gateway.engine.warm
export OPENBLAS_NUM_THREADS=1 PYTHONDONTWRITEBYTECODE=1
export BSC_VM_VCANS=${BSC_VM_VCANS:-4} BSC_VM_TIMEOUT=${BSC_VM_TIMEOUT:-900}
# -p no:cacheprovider: the guest would write .pytest_cache into the host tree as root
PYTEST=(.venv/bin/python -m pytest -q -p no:cacheprovider)
selected=0
for a in "$@"; do if [ -e "${a%%::*}" ]; then selected=1; fi; done
if [ $selected = 0 ]; then
  rc=0
  listing=$(env -u PYTHONDONTWRITEBYTECODE "${PYTEST[@]}" --collect-only -m vcan 2>&1) || rc=$?
  if [ $rc -ne 0 ]; then
    printf '%s\n' "$listing" | tail -n 30
    echo "vcan-tier: collecting the vcan tests on the host failed (pytest exit $rc)" >&2
    exit $rc
  fi
  mapfile -t files < <(printf '%s\n' "$listing" | sed -n 's/^\([^ ]*\.py\)::.*/\1/p' | sort -u)
  [ ${#files[@]} -gt 0 ] || { echo "vcan-tier: no test marked vcan was collected" >&2; exit 5; }
  set -- "$@" "${files[@]}"
fi
start=$SECONDS
rc=0
.ci/vcan-vm.sh "${PYTEST[@]}" -m vcan "$@" || rc=$?
echo "vcan-tier: exit $rc after $((SECONDS - start)) s in the VM" >&2
exit $rc
