#!/usr/bin/env bash
# Remove the lidar-avoid companion service installed by systemd/install.sh (see docs/companion.md, "4. The service").
#
#   sudo systemd/uninstall.sh [--purge]
#
# Stops and disables the unit, removes it and /opt/lidar-avoid (virtual environment, README).
# Configuration (/etc/lidar-avoid), state (/var/lib/lidar-avoid: TensorRT engine cache), logs
# (/var/log/lidar-avoid) and the service user stay unless --purge is given.
#
# --root DIR   operate below DIR instead of / (a staged image, tests); nothing is stopped, and
#              the user is left in DIR/etc/passwd (remove it with userdel --root if wanted).
# --dry-run    print every action, change nothing.
set -euo pipefail

UNIT=lidar-avoid-companion.service
PREFIX=/opt/lidar-avoid
ROOT=""
DRY=0
PURGE=0

usage() { echo "usage: $0 [--root DIR] [--dry-run] [--purge]"; }
die() { echo "uninstall.sh: error: $*" >&2; exit 2; }

while [ $# -gt 0 ]; do
    case "$1" in
        --root) [ $# -ge 2 ] || die "--root needs a directory"; ROOT="${2%/}"; shift 2 ;;
        --dry-run) DRY=1; shift ;;
        --purge) PURGE=1; shift ;;
        -h|--help) usage; exit 0 ;;
        *) usage >&2; die "unknown argument: $1" ;;
    esac
done

run() {
    printf '+ %s\n' "$*"
    [ "$DRY" = 1 ] || "$@"
}

if [ -n "$ROOT" ]; then
    [ "$DRY" = 1 ] || [ -d "$ROOT" ] || die "--root $ROOT is not a directory"
elif [ "$DRY" = 0 ] && [ "$(id -u)" != 0 ]; then
    die "run as root (sudo), or use --dry-run / --root DIR"
fi

echo "== systemd unit"
if [ -e "$ROOT/etc/systemd/system/$UNIT" ] || [ "$DRY" = 1 ]; then
    if [ -n "$ROOT" ]; then
        run systemctl --root="$ROOT" disable "$UNIT"
    else
        run systemctl disable --now "$UNIT"
    fi
    run rm -f "$ROOT/etc/systemd/system/$UNIT"
    [ -n "$ROOT" ] || run systemctl daemon-reload
else
    echo "no $UNIT installed"
fi

echo "== program files $PREFIX"
run rm -rf "$ROOT$PREFIX"

if [ "$PURGE" = 1 ]; then
    echo "== configuration, state, logs, service user (--purge)"
    run rm -rf "$ROOT/etc/lidar-avoid" "$ROOT/var/lib/lidar-avoid" "$ROOT/var/log/lidar-avoid"
    run rm -f "$ROOT/etc/sysusers.d/lidar-avoid.conf"
    if [ -n "$ROOT" ]; then
        echo "user lidar-avoid left in $ROOT/etc/passwd (userdel --root $ROOT lidar-avoid removes it)"
    elif getent passwd lidar-avoid >/dev/null || [ "$DRY" = 1 ]; then
        run userdel lidar-avoid
    fi
else
    echo "kept /etc/lidar-avoid, /var/lib/lidar-avoid, /var/log/lidar-avoid and user lidar-avoid (--purge removes them)"
fi
[ "$DRY" = 0 ] || echo "(dry run: nothing was changed)"
