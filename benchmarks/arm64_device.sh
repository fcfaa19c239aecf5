#!/usr/bin/env bash
# An emulated arm64 board on this machine (docs/devices.md §7): an arm64 Debian bookworm root run by
# qemu-user, with its own sshd on 127.0.0.1, Python 3.11, a lean bench-matrix and the runtimes' aarch64 wheels
#   benchmarks/arm64_device.sh build    # once (as root): the root, cached under $BM_ARM64 (~/.cache/...)
#   benchmarks/arm64_device.sh start    # its sshd, with a throwaway key; prints the --device argument
#   benchmarks/arm64_device.sh stop     # stops it and unmounts what start mounted
set -euo pipefail

REPO=$(cd "$(dirname "$0")/.." && pwd)
CACHE=${BM_ARM64:-$HOME/.cache/bench-matrix/arm64}
ROOT=$CACHE/root
PORT=${BM_ARM64_PORT:-2222}
NAME=arm64-qemu  # the board's host name, and the ssh config's alias for it
PYTHON=/opt/bm/bin/python
CPU=cortex-a76  # the core qemu emulates: a Raspberry Pi 5's
# what measuring needs: bench-matrix itself (no extra) and the CPU runtimes with aarch64 wheels on PyPI
RUNTIMES=(onnxruntime ai-edge-litert openvino)

need_root() {
  [ "$(id -u)" = 0 ] || { echo "run it as root (it mounts and chroots)" >&2; exit 2; }
}

binfmt() {
  # qemu-user runs the root's arm64 programs: binfmt_misc hands them to qemu-aarch64-static
  command -v qemu-aarch64-static mmdebstrap >/dev/null || {
    echo "needs: apt-get install qemu-user-static binfmt-support mmdebstrap" >&2; exit 2; }
  mountpoint -q /proc/sys/fs/binfmt_misc || mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc
  [ -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ] || update-binfmts --enable qemu-aarch64
}

wheels() {
  # the aarch64 wheels for bookworm's glibc 2.36, downloaded here (fast) at the versions requirements.lock
  # pins, installed there offline
  local py=$REPO/.venv/bin/python platforms=(--platform manylinux2014_aarch64)
  for glibc in $(seq 17 36); do platforms+=(--platform "manylinux_2_${glibc}_aarch64"); done  # pip names each
  [ -x "$py" ] || py=python3
  rm -rf "$CACHE/wheels" && mkdir -p "$CACHE/wheels"
  "$py" -m pip wheel --quiet --no-deps "$REPO" -w "$CACHE/wheels"
  "$py" -m pip download --quiet --only-binary=:all: --python-version 3.11 --implementation cp --abi cp311 \
    "${platforms[@]}" -c "$REPO/requirements.lock" -d "$CACHE/wheels" \
    "$CACHE"/wheels/bench_matrix-*.whl "${RUNTIMES[@]}"
}

build() {
  need_root; binfmt
  local start=$SECONDS
  if [ ! -x "$ROOT/usr/bin/python3" ]; then
    rm -rf "$ROOT" && mkdir -p "$CACHE"
    mmdebstrap --arch=arm64 --variant=apt \
      --include=python3,python3-venv,openssh-server,libgomp1,hostname,procps bookworm "$ROOT"
  fi
  wheels
  rm -rf "$ROOT/tmp/wheels" && cp -r "$CACHE/wheels" "$ROOT/tmp/wheels"
  if [ -x "$ROOT$PYTHON" ]; then  # built before: this checkout's bench-matrix only
    chroot "$ROOT" "$PYTHON" -m pip install --quiet --no-index --no-deps --force-reinstall \
      "/tmp/wheels/$(basename "$CACHE"/wheels/bench_matrix-*.whl)"
  else
    chroot "$ROOT" python3 -m venv /opt/bm
    chroot "$ROOT" "$PYTHON" -m pip install --quiet --no-index --find-links /tmp/wheels \
      bench-matrix "${RUNTIMES[@]}"
  fi
  rm -rf "$ROOT/tmp/wheels"
  echo "built $ROOT in $((SECONDS - start)) s: $(du -sh "$ROOT" | cut -f1)"
}

cpuinfo() {
  # qemu 7.2 shows arm64 programs the x86 host's /proc/cpuinfo, and ONNX Runtime's CPU detection dies
  # reading it (SIGSEGV at import; qemu 8.1+ emulates the file): the board gets the kernel's layout for
  # the Cortex-A76 it emulates (a Raspberry Pi 5's core: fp16, int8 dot product, no SVE), one per core
  local core
  for core in $(seq 0 $(($(nproc) - 1))); do
    printf 'processor\t: %s\nBogoMIPS\t: 108.00\nFeatures\t: %s\nCPU implementer\t: 0x41\n' "$core" \
      "fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics fphp asimdhp cpuid asimdrdm lrcpc dcpop asimddp"
    printf 'CPU architecture: 8\nCPU variant\t: 0x4\nCPU part\t: 0xd0b\nCPU revision\t: 1\n\n'
  done > "$CACHE/cpuinfo"
  mount --bind "$CACHE/cpuinfo" "$ROOT/proc/cpuinfo"
}

start() {
  need_root; binfmt
  [ -x "$ROOT$PYTHON" ] || { echo "no board yet: run $0 build" >&2; exit 2; }
  stop quietly
  for dir in proc sys dev; do mount --rbind "/$dir" "$ROOT/$dir" && mount --make-rslave "$ROOT/$dir"; done
  cpuinfo
  mkdir -p "$ROOT/run/sshd" "$ROOT/root/.ssh" "$ROOT/etc/bm"
  rm -f "$CACHE/key" "$CACHE/key.pub"
  ssh-keygen -q -t ed25519 -N "" -C throwaway -f "$CACHE/key"
  cp "$CACHE/key.pub" "$ROOT/root/.ssh/authorized_keys"
  echo "QEMU_CPU=$CPU" > "$ROOT/root/.ssh/environment"  # every program qemu starts there emulates it
  printf '%s\n' "Port $PORT" "ListenAddress 127.0.0.1" "PidFile /run/bm-sshd.pid" "UsePAM no" \
    "PasswordAuthentication no" "KbdInteractiveAuthentication no" "PermitRootLogin prohibit-password" \
    "PermitUserEnvironment QEMU_CPU" "LogLevel ERROR" > "$ROOT/etc/bm/sshd_config"
  printf '%s\n' "Host $NAME" "  HostName 127.0.0.1" "  Port $PORT" "  User root" "  IdentityFile $CACHE/key" \
    "  IdentitiesOnly yes" "  StrictHostKeyChecking no" "  UserKnownHostsFile /dev/null" "  LogLevel ERROR" \
    > "$CACHE/ssh_config"
  # its own host name (a UTS namespace), so that records name the board, not this machine
  QEMU_CPU=$CPU unshare --uts sh -c "hostname $NAME && exec chroot '$ROOT' /usr/sbin/sshd -f /etc/bm/sshd_config"
  for _ in $(seq 60); do
    ssh -F "$CACHE/ssh_config" -o BatchMode=yes "$NAME" true 2>/dev/null && break
    sleep 1
  done
  echo "started: $(ssh -F "$CACHE/ssh_config" -o BatchMode=yes "$NAME" uname -nm)"
  echo "--device $NAME=$PYTHON --ssh-config $CACHE/ssh_config"
}

stop() {
  local pid
  if [ -f "$ROOT/run/bm-sshd.pid" ]; then
    pid=$(cat "$ROOT/run/bm-sshd.pid")
    kill "$pid" 2>/dev/null || true
    rm -f "$ROOT/run/bm-sshd.pid"
  fi
  for dir in dev sys proc; do
    # lazily where a mount below is still busy (seen with /dev after the sshd had ended)
    if mountpoint -q "$ROOT/$dir"; then umount -R "$ROOT/$dir" 2>/dev/null || umount -R -l "$ROOT/$dir"; fi
  done
  [ "${1:-}" = quietly ] || echo "stopped"
}

case "${1:-}" in
  build) build ;;
  start) start ;;
  stop) stop ;;
  *) echo "usage: $0 build|start|stop" >&2; exit 2 ;;
esac
