#!/usr/bin/env bash
# Install the lidar-avoid companion as a systemd service (see docs/companion.md, "4. The service").
#
#   sudo systemd/install.sh [--model policy.onnx] [--ort-wheel onnxruntime_gpu-....whl] [--now]
#
# Steps: service user (systemd-sysusers), virtual environment in /opt/lidar-avoid/venv with the
# base install only (the companion's runtime, ArduPilot and PX4 (mavsdk) alike: no torch), config in /etc/lidar-avoid (an existing
# companion.toml is never overwritten), the unit in /etc/systemd/system, enable it.
#
# --root DIR   install below DIR instead of / (staging an image, tests): users are created with
#              systemd-sysusers --root, the unit is enabled with systemctl --root, nothing is
#              started. A virtual environment is not relocatable: build it on the target, or pass
#              --no-venv when staging.
# --dry-run    print every action, change nothing.
set -euo pipefail

SRC_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
UNIT=lidar-avoid-companion.service
PREFIX=/opt/lidar-avoid
CONF_DIR=/etc/lidar-avoid

ROOT=""
DRY=0
VENV=1
ENABLE=1
START=0
MODEL=""
ORT_WHEEL=""
PYTHON=python3
SOURCE="$SRC_DIR"

usage() {
    cat <<EOF
usage: $0 [--root DIR] [--dry-run] [--model FILE] [--ort-wheel WHEEL] [--source SPEC]
          [--python PY] [--no-venv] [--no-enable] [--now]
  --root DIR        install below DIR instead of / (staging, tests); nothing is started
  --dry-run         print the actions, change nothing
  --model FILE      copy this ONNX policy to $CONF_DIR/policy.onnx (the example config's policy.model)
  --ort-wheel WHEEL replace the CPU onnxruntime with this onnxruntime-gpu wheel (NVIDIA's Jetson build)
  --source SPEC     what to pip install (default: this checkout, $SRC_DIR); base install, no extras
  --python PY       interpreter for the virtual environment (default python3)
  --no-venv         skip the virtual environment
  --no-enable       install the unit but do not enable it
  --now             start the service after enabling it (not with --root)
EOF
}

die() { echo "install.sh: error: $*" >&2; exit 2; }

while [ $# -gt 0 ]; do
    case "$1" in
        --root) [ $# -ge 2 ] || die "--root needs a directory"; ROOT="${2%/}"; shift 2 ;;
        --dry-run) DRY=1; shift ;;
        --model) [ $# -ge 2 ] || die "--model needs a file"; MODEL="$2"; shift 2 ;;
        --ort-wheel) [ $# -ge 2 ] || die "--ort-wheel needs a wheel"; ORT_WHEEL="$2"; shift 2 ;;
        --source) [ $# -ge 2 ] || die "--source needs a pip requirement"; SOURCE="$2"; shift 2 ;;
        --python) [ $# -ge 2 ] || die "--python needs an interpreter"; PYTHON="$2"; shift 2 ;;
        --no-venv) VENV=0; shift ;;
        --no-enable) ENABLE=0; shift ;;
        --now) START=1; shift ;;
        -h|--help) usage; exit 0 ;;
        *) usage >&2; die "unknown argument: $1" ;;
    esac
done

# Print each action; run it unless --dry-run.
run() {
    printf '+ %s\n' "$*"
    [ "$DRY" = 1 ] || "$@"
}

need() { command -v "$1" >/dev/null || die "$1 not found ($2)"; }

if [ -n "$ROOT" ]; then
    [ "$START" = 0 ] || die "--now cannot start a service installed with --root"
    [ "$DRY" = 1 ] || [ -d "$ROOT" ] || die "--root $ROOT is not a directory"
elif [ "$DRY" = 0 ] && [ "$(id -u)" != 0 ]; then
    die "run as root (sudo), or use --dry-run / --root DIR"
fi
[ -z "$MODEL" ] || [ -f "$MODEL" ] || die "--model $MODEL: no such file"
[ -z "$ORT_WHEEL" ] || [ "$VENV" = 1 ] || die "--ort-wheel needs the virtual environment (drop --no-venv)"
for f in systemd/$UNIT systemd/lidar-avoid.sysusers config/companion.example.toml; do
    [ -f "$SRC_DIR/$f" ] || die "$SRC_DIR/$f missing: run from a lidar-avoid checkout"
done
if [ "$DRY" = 0 ]; then
    need systemd-sysusers "the systemd package provides it"
    need systemctl "the systemd package provides it"
fi

echo "== service user (systemd-sysusers)"
run install -D -m 0644 "$SRC_DIR/systemd/lidar-avoid.sysusers" "$ROOT/etc/sysusers.d/lidar-avoid.conf"
if [ -n "$ROOT" ]; then
    run systemd-sysusers --root="$ROOT" "$ROOT/etc/sysusers.d/lidar-avoid.conf"
else
    run systemd-sysusers /etc/sysusers.d/lidar-avoid.conf
fi

if [ "$VENV" = 1 ]; then
    echo "== virtual environment $PREFIX/venv (base install: the companion runtime, no torch)"
    VENV_DIR="$ROOT$PREFIX/venv"
    run "$PYTHON" -m venv "$VENV_DIR"
    run "$VENV_DIR/bin/pip" install --upgrade pip
    run "$VENV_DIR/bin/pip" install "$SOURCE"
    if [ -n "$ORT_WHEEL" ]; then
        # onnxruntime-gpu installs the same "onnxruntime" module: remove the CPU build first.
        run "$VENV_DIR/bin/pip" uninstall -y onnxruntime
        run "$VENV_DIR/bin/pip" install "$ORT_WHEEL"
    fi
    # The companion must never need torch; a dependency that drags it in is a packaging bug.
    run "$VENV_DIR/bin/python" -c \
        "import importlib.util, sys; sys.exit('torch is installed in the companion venv' if importlib.util.find_spec('torch') else 0)"
    run "$VENV_DIR/bin/avoid-companion" --help
    # PX4's link (mavsdk, in the base install) must load here, not at the first flight: a wheel
    # built for a newer glibc than the Jetson's fails on import.
    run "$VENV_DIR/bin/python" -c "import companion.autopilot.px4"
fi

echo "== configuration $CONF_DIR"
run install -d -m 0755 "$ROOT$CONF_DIR" "$ROOT$CONF_DIR/firmware_params"
if [ -e "$ROOT$CONF_DIR/companion.toml" ]; then
    echo "kept existing $CONF_DIR/companion.toml"
else
    run install -m 0644 "$SRC_DIR/config/companion.example.toml" "$ROOT$CONF_DIR/companion.toml"
    echo "edit $CONF_DIR/companion.toml (policy.model, autopilot.type/connect) before starting"
fi
for f in "$SRC_DIR"/firmware_params/*; do
    run install -m 0644 "$f" "$ROOT$CONF_DIR/firmware_params/"
done
[ -z "$MODEL" ] || run install -m 0644 "$MODEL" "$ROOT$CONF_DIR/policy.onnx"
run install -D -m 0644 "$SRC_DIR/README.md" "$ROOT$PREFIX/README.md"

echo "== systemd unit"
run install -D -m 0644 "$SRC_DIR/systemd/$UNIT" "$ROOT/etc/systemd/system/$UNIT"
if [ -n "$ROOT" ]; then
    [ "$ENABLE" = 0 ] || run systemctl --root="$ROOT" enable "$UNIT"
else
    run systemctl daemon-reload
    [ "$ENABLE" = 0 ] || run systemctl enable "$UNIT"
    [ "$START" = 0 ] || run systemctl start "$UNIT"
fi

echo "== done"
[ "$DRY" = 0 ] || echo "(dry run: nothing was changed)"
if [ -z "$ROOT" ] && [ "$START" = 0 ]; then
    echo "start with: sudo systemctl start $UNIT; follow with: journalctl -u $UNIT -f"
fi
