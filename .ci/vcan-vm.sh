#!/usr/bin/env bash
# vcan-vm.sh: run one command in a throw-away QEMU guest that has real SocketCAN (vcan).
#
#   .ci/vcan-vm.sh [--] COMMAND [ARGS...]        exit status = COMMAND's exit status
#   e.g.  .ci/vcan-vm.sh ip -br link
#         BSC_VM_VCANS=3 .ci/vcan-vm.sh .venv/bin/python -m pytest -m vcan tests/system/vcan
#
# Why: the CI host's kernel has no CAN modules, so the SocketCAN tier boots a stock Debian
# kernel (which has them) under QEMU and runs the command there. Adapted for bsc from
# ../shared/tools/run-in-vm.sh, trimmed to what the vcan tier needs.
#
# What the command sees: the host's root filesystem (virtio-9p, read-write, as root: it
# writes the host's files for real), the same working directory, the caller's exported
# environment (so the host's .venv works as is), lo and vcan0..vcan<N-1> up and nothing else
# on the network, 8 MiB socket receive buffers (net.core.rmem_default: a receiver starved of
# the one vCPU by a lockstep sender keeps every frame), stdin /dev/null, BSC_VM=1 and BSC_VM_VCANS=<N> set, TMPDIR on a guest
# tmpfs (pytest's capture ftruncate()s unlinked temp files, which 9p cannot do).
# stdout and stderr come back merged on this script's stdout.
#
# First run (then cached under BSC_VM_CACHE): apt-get installs qemu-system-x86 and
# busybox-static if missing (needs root; qemu also when only the image is cached),
# `apt-get download`s Debian's current linux-image-amd64 (~70 MB), unpacks it with dpkg -x
# (the host's /boot and /lib/modules are not touched), and builds a small initramfs with
# busybox and the CAN + 9p modules (about 15 s in all).
# The image is rebuilt when its recipe in this script (the guest's /init, the build steps, the
# module list) changes, or with BSC_VM_REBUILD=1. A missing or stale cache is rebuilt the same way.
#
# Knobs (environment, optional):
#   BSC_VM_VCANS=1       number of vcan interfaces, vcan0..vcan<N-1>   (default 1)
#   BSC_VM_FD=1          1: CAN FD capable (mtu 72); 0: classic only (mtu 16)  (default 1)
#   BSC_VM_MEM=1024      guest RAM, MiB
#   BSC_VM_TIMEOUT=1800  wall-clock limit of the whole run, s (exit 124 when hit)
#   BSC_VM_BOOT_TIMEOUT=120  limit until the guest starts COMMAND, s: a VM that does not boot
#                        (kernel hang, 9p mount stuck) fails fast with exit 125, not after TIMEOUT
#   BSC_VM_ACCEL=tcg     tcg | kvm. Default tcg: this machine's /dev/kvm is nested and cannot
#                        run a stock kernel. Under TCG, boot ~3 s, Python ~14x slower.
#   BSC_VM_CACHE=DIR     kernel, initramfs, job dirs (default ${XDG_CACHE_HOME:-~/.cache}/bsc-vcan-vm;
#                        no commas: QEMU option syntax)
#   BSC_VM_REBUILD=1     rebuild the image;  BSC_VM_DEBUG=1  kernel + init messages;
#   BSC_VM_KEEP=1        keep the job dir
# Exit status besides COMMAND's: 124 timeout, 125 VM or setup failure, 2 usage.
set -uo pipefail
SELF=$(readlink -f "${BASH_SOURCE[0]}")
CACHE=${BSC_VM_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/bsc-vcan-vm}
[ "${1:-}" = "--" ] && shift
[ $# -ge 1 ] || { echo "usage: $0 [--] COMMAND [ARGS...]" >&2; exit 2; }
die() { echo "vcan-vm: $*" >&2; exit 125; }

NVCAN=${BSC_VM_VCANS:-1}; FD=${BSC_VM_FD:-1}; MEM=${BSC_VM_MEM:-1024}
TIMEOUT=${BSC_VM_TIMEOUT:-1800}; ACCEL=${BSC_VM_ACCEL:-tcg}; DEBUG=${BSC_VM_DEBUG:-0}
BOOT_TIMEOUT=${BSC_VM_BOOT_TIMEOUT:-120}
[[ "$NVCAN" =~ ^[0-9]+$ ]] && [ "$NVCAN" -le 16 ] || die "BSC_VM_VCANS must be 0..16, not '$NVCAN'"
[[ "$TIMEOUT" =~ ^[0-9]+$ ]] && [[ "$BOOT_TIMEOUT" =~ ^[0-9]+$ ]] || die "BSC_VM_TIMEOUT and BSC_VM_BOOT_TIMEOUT are whole seconds"
[[ "$CACHE" != *,* ]] || die "the cache path may not contain a comma: $CACHE"
MODULES=(virtio_pci 9pnet_virtio 9p can can_raw can_bcm can_dev vcan)

# ------------------------------------------------------------------ the guest's /init
# Runs as PID 1 from the initramfs: load modules, mount the host root over 9p, bring the
# vcans up, chroot into the host root to run the job, write its status, power off.
guest_init() {
cat <<'INIT'
#!/bin/busybox sh
/bin/busybox --install -s /bin
export PATH=/bin
mount -t proc proc /proc; mount -t sysfs sys /sys; mount -t devtmpfs dev /dev
DEBUG=0; NVCAN=1; FD=1
for arg in $(cat /proc/cmdline); do
  case "$arg" in
    bscvm.debug=*) DEBUG=${arg#*=} ;;
    bscvm.vcans=*) NVCAN=${arg#*=} ;;
    bscvm.fd=*) FD=${arg#*=} ;;
  esac
done
say() { [ "$DEBUG" = 1 ] && echo "[bsc-vm] $*"; return 0; }
halt() { echo "[bsc-vm] FATAL: $*"; echo 0 > /proc/sys/kernel/printk; poweroff -f; }
stty -F /dev/console -onlcr 2>/dev/null            # keep \n as \n on the serial console
while read -r ko; do
  name=$(basename "$ko" .ko | tr - _)
  insmod "/lib/modules/$ko" 2>/dev/null || [ -e "/sys/module/$name" ] || echo "[bsc-vm] insmod $ko failed"
done < /modules.order
say "modules loaded at $(cut -d' ' -f1 /proc/uptime) s"
R=/newroot
mount -t 9p -o trans=virtio,version=9p2000.L,msize=512000,cache=loose hostroot $R || halt "9p mount of the host root"
mount -t 9p -o trans=virtio,version=9p2000.L,cache=none bscjob /job || halt "9p mount of the job dir"
mount -t proc proc $R/proc; mount -t sysfs sys $R/sys; mount -t devtmpfs dev $R/dev
mkdir -p $R/dev/pts $R/dev/shm
mount -t devpts -o ptmxmode=666 devpts $R/dev/pts
mount -t tmpfs -o mode=1777 shm $R/dev/shm
mount -t tmpfs -o mode=755 run $R/run
mkdir -p $R/run/bsc-vm-job && mount --bind /job $R/run/bsc-vm-job
ip link set lo up
MTU=16; [ "$FD" = 1 ] && MTU=72
i=0
while [ $i -lt "$NVCAN" ]; do
  ip link add dev vcan$i type vcan || halt "ip link add vcan$i"
  ip link set vcan$i mtu $MTU || halt "mtu $MTU on vcan$i"
  ip link set vcan$i up || halt "ip link set vcan$i up"
  i=$((i + 1))
done
# 8 MiB socket receive buffers (default ~210 kB, 278 CAN frames): under TCG a receiver that
# loses the CPU to a lockstep sender for a while must not lose frames, which a real host
# running at real-time rates never needs
echo 8388608 > /proc/sys/net/core/rmem_default; echo 8388608 > /proc/sys/net/core/rmem_max
hostname bsc-vm
say "job starts at $(cut -d' ' -f1 /proc/uptime) s"
: > /job/booted                                     # the host's boot watchdog stops here
SH=/bin/sh; [ -x $R/bin/bash ] && SH=/bin/bash
chroot $R $SH /run/bsc-vm-job/inner.sh </dev/null
echo $? > /job/rc
sync
echo 0 > /proc/sys/kernel/printk
poweroff -f
INIT
}

# ------------------------------------------------------------- one-time image build
# What the image is made from; its hash in $CACHE/stamp decides a rebuild.
recipe() { { declare -f guest_init build_image; echo "${MODULES[*]}"; } | md5sum | cut -c1-32; }

# Debian packages this runner needs on the host, installed with apt-get when missing (root).
ensure_packages() {
  local missing=() p
  for p in "$@"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  [ "$(id -u)" = 0 ] || die "install ${missing[*]} first (apt-get, as root)"
  command -v apt-get >/dev/null || die "install ${missing[*]} first (no apt-get here)"
  echo "vcan-vm: installing ${missing[*]}" >&2
  apt-get update -qq >&2 || die "apt-get update failed"
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >&2 \
    || die "apt-get install ${missing[*]} failed"
}

build_image() {
  set -e
  ensure_packages busybox-static
  local kpkg
  kpkg=$(apt-cache depends linux-image-amd64 2>/dev/null | awk '/Depends: linux-image-[0-9]/{print $2; exit}')
  if [ -z "$kpkg" ]; then
    apt-get update -qq >&2
    kpkg=$(apt-cache depends linux-image-amd64 | awk '/Depends: linux-image-[0-9]/{print $2; exit}')
  fi
  [ -n "$kpkg" ] || die "apt-cache cannot resolve linux-image-amd64"
  local kver=${kpkg#linux-image-} work deb
  work=$(mktemp -d "$CACHE/build.XXXXXX")
  trap 'rm -rf "$work"' RETURN
  echo "vcan-vm: building the VM image for kernel $kver in $CACHE" >&2
  mkdir -p "$CACHE/debs"
  deb=$(ls "$CACHE/debs/${kpkg}"_*.deb 2>/dev/null | tail -1 || true)
  if [ -z "$deb" ]; then
    rm -f "$CACHE/debs"/linux-image-*.deb
    (cd "$CACHE/debs" && apt-get download -q "$kpkg" >&2) || die "apt-get download $kpkg failed"
    deb=$(ls "$CACHE/debs/${kpkg}"_*.deb | tail -1)
  fi
  dpkg -x "$deb" "$work/k"
  local moddir=$work/k/lib/modules/$kver ird=$work/initramfs
  # The stock bzImage is xz-compressed; decompressing it under TCG costs seconds per boot.
  # Boot the ELF vmlinux inside it directly (QEMU -kernel takes it through the PVH entry).
  python3 - "$work/k/boot/vmlinuz-$kver" "$work/vmlinux" <<'PY'
import lzma, sys
blob = open(sys.argv[1], "rb").read()
at = blob.find(b"\xfd7zXZ\x00")
elf = b""
if at >= 0:
    elf = lzma.LZMADecompressor(format=lzma.FORMAT_XZ).decompress(blob[at:])
open(sys.argv[2], "wb").write(elf if elf[:4] == b"\x7fELF" else blob)
PY
  mkdir -p "$ird"/{bin,dev,proc,sys,newroot,job,lib/modules}
  cp /bin/busybox "$ird/bin/busybox"
  guest_init > "$ird/init"; chmod 755 "$ird/init"
  # Module load order from each .ko's modinfo "depends=" (depmod is not needed for insmod).
  python3 - "$moddir" "${MODULES[@]}" > "$ird/modules.order" <<'PY'
import os, re, sys
root, wanted = sys.argv[1], sys.argv[2:]
path = {}
for d, _, names in os.walk(root):
    for n in names:
        if n.endswith(".ko"):
            path[n[:-3].replace("-", "_")] = os.path.join(d, n)
order, done = [], set()
def need(mod):
    mod = mod.replace("-", "_")
    if mod in done:
        return
    done.add(mod)
    if mod not in path:
        sys.exit(f"kernel module {mod} not in the image")
    m = re.search(rb"(?:^|\x00)depends=([^\x00]*)\x00", open(path[mod], "rb").read())
    for dep in (m.group(1).decode().split(",") if m else ()):
        if dep:
            need(dep)
    order.append(os.path.relpath(path[mod], root))
for w in wanted:
    need(w)
print("\n".join(order))
PY
  while read -r ko; do
    mkdir -p "$ird/lib/modules/$(dirname "$ko")"; cp "$moddir/$ko" "$ird/lib/modules/$ko"
  done < "$ird/modules.order"
  (cd "$ird" && find . | /bin/busybox cpio -o -H newc 2>/dev/null | gzip -1) > "$work/initramfs.cpio.gz"
  mv "$work/vmlinux" "$CACHE/vmlinux"
  mv "$work/initramfs.cpio.gz" "$CACHE/initramfs.cpio.gz"
  echo "$kver $(recipe)" > "$CACHE/stamp"
  set +e
}

command -v qemu-system-x86_64 >/dev/null || ensure_packages qemu-system-x86
command -v qemu-system-x86_64 >/dev/null || die "qemu-system-x86_64 is missing"
mkdir -p "$CACHE/jobs" || die "cannot create $CACHE"
want=" $(recipe)"
image_ok() {
  [ -s "$CACHE/vmlinux" ] && [ -s "$CACHE/initramfs.cpio.gz" ] && [[ "$(cat "$CACHE/stamp" 2>/dev/null)" == *"$want" ]]
}
if [ "${BSC_VM_REBUILD:-0}" = 1 ] || ! image_ok; then
  # one builder at a time; a second caller waits and then finds the image built
  ( exec 9>"$CACHE/build.lock"; flock 9
    if [ "${BSC_VM_REBUILD:-0}" = 1 ] || ! image_ok; then build_image; fi
  ) || die "building the VM image failed"
fi

# ------------------------------------------------------------------------ the job
JOB=$(mktemp -d "$CACHE/jobs/job.XXXXXX") || die "cannot make a job dir"
[ "${BSC_VM_KEEP:-0}" = 1 ] || trap 'rm -rf "$JOB"' EXIT
# the caller's exported environment, minus what belongs to this host session
export -p | grep -v -E '^declare -[a-zA-Z-]* (PWD|OLDPWD|SHLVL|_|HOSTNAME|TMPDIR|SHELLOPTS|BASHOPTS|SSH_[A-Z_]*|DISPLAY|XDG_RUNTIME_DIR|DBUS_SESSION_BUS_ADDRESS)(=|$)' > "$JOB/env.sh"
TTY=0; [ -t 1 ] && TTY=1
{ printf 'cd -- %q || exit 125\n' "$PWD"
  printf 'export BSC_VM=1 BSC_VM_VCANS=%q\n' "$NVCAN"
  printf 'mkdir -p /run/bsc-vm-tmp && chmod 1777 /run/bsc-vm-tmp && export TMPDIR=/run/bsc-vm-tmp\n'
  if [ $TTY = 1 ]; then
    cols=$(stty size 2>/dev/null </dev/tty | cut -d' ' -f2)
    [ -n "$cols" ] && [ -z "${COLUMNS:-}" ] && printf 'export COLUMNS=%q\n' "$cols"   # the serial line has no size
    printf 'exec'; printf ' %q' "$@"; printf '\n'
  else
    # keep stdout a pipe, as it is on the host (tools change output on a tty)
    printf '%q ' "$@"; printf '2>&1 | cat\nexit ${PIPESTATUS[0]}\n'
  fi
} > "$JOB/cmd.sh"
printf '. /run/bsc-vm-job/env.sh\n. /run/bsc-vm-job/cmd.sh\n' > "$JOB/inner.sh"

# TCG's CPU: the most it emulates, but without AVX2. QEMU 7.2 (Debian 12's) emulates some AVX2
# instruction wrongly: numpy 2.x's AVX2 argsort (x86-simd-sort) returned index arrays that are not
# permutations (int64 arrays of 9-16, 37-40, ... elements) and so read out of bounds; the gateway
# died of SIGSEGV in np.argsort in the recorder's thread (2026-11-26). The same sorts are right on
# the host, on its AVX-512 and AVX2 paths. tests/system/vcan/test_vm_cpu.py checks it in here.
case "$ACCEL" in
  kvm) ACC=(-accel kvm -cpu host) ;;
  tcg) ACC=(-accel tcg,thread=multi -cpu max,-avx2) ;;
  *) die "BSC_VM_ACCEL must be tcg or kvm, not '$ACCEL'" ;;
esac
LOGLEVEL=1; [ "$DEBUG" = 1 ] && LOGLEVEL=7
APPEND="console=ttyS0 loglevel=$LOGLEVEL panic=-1 edd=off tsc=reliable no_timer_check mitigations=off"
APPEND+=" rcupdate.rcu_expedited=1 bscvm.debug=$DEBUG bscvm.vcans=$NVCAN bscvm.fd=$FD"

# qemu in the background, so that a guest that never reaches the command is caught early
timeout -k 10 "$TIMEOUT" qemu-system-x86_64 "${ACC[@]}" \
  -machine q35 -bios /usr/share/qemu/qboot.rom -nodefaults -no-user-config \
  -m "$MEM" -smp 1 -display none -monitor none -serial stdio -no-reboot \
  -kernel "$CACHE/vmlinux" -initrd "$CACHE/initramfs.cpio.gz" -append "$APPEND" \
  -fsdev local,id=hostroot,path=/,security_model=none,multidevs=remap \
  -device virtio-9p-pci,fsdev=hostroot,mount_tag=hostroot \
  -fsdev local,id=job,path="$JOB",security_model=none \
  -device virtio-9p-pci,fsdev=job,mount_tag=bscjob \
  < /dev/null &
QPID=$!
cleanup() { kill "$QPID" 2>/dev/null; wait "$QPID" 2>/dev/null; [ "${BSC_VM_KEEP:-0}" = 1 ] || rm -rf "$JOB"; }
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
boot_by=$((SECONDS + BOOT_TIMEOUT))
while [ ! -e "$JOB/booted" ] && kill -0 "$QPID" 2>/dev/null; do
  if [ "$SECONDS" -ge "$boot_by" ]; then
    echo "vcan-vm: the VM did not start the command within ${BOOT_TIMEOUT} s (BSC_VM_BOOT_TIMEOUT);" \
         "stopped it. Retry with BSC_VM_DEBUG=1 to see the kernel and init messages" >&2
    exit 125
  fi
  sleep 0.2
done
wait "$QPID"
qrc=$?
if [ -s "$JOB/rc" ]; then
  exit "$(cat "$JOB/rc")"
elif [ $qrc = 124 ] || [ $qrc = 137 ]; then
  echo "vcan-vm: timed out after ${TIMEOUT} s" >&2; exit 124
fi
echo "vcan-vm: the VM stopped (qemu status $qrc) without the command's status; retry with BSC_VM_DEBUG=1" >&2
exit 125
