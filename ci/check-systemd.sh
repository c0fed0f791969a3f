#!/usr/bin/env bash
# CI: check the companion's systemd unit (or the unit given as $1).
#  1. systemd-analyze verify: any message at all fails (verify exits 0 on unknown keys and bad
#     values, it only prints them). The unit is verified inside a scratch root holding the host's
#     stock units and a stand-in for the ExecStart binary, so the check runs without the venv.
#  2. systemd-analyze security: prints the exposure table and fails above 4.0 (target ≤ 4.0).
# Debian's systemd package provides systemd-analyze; it is installed here when missing (CI runs as
# root with apt). Where it cannot be installed the check is skipped with a message, unless
# REQUIRE_SYSTEMD_ANALYZE=1.
set -euo pipefail
cd "$(dirname "$0")/.."
UNIT_FILE="${1:-systemd/lidar-avoid-companion.service}"
MAX_EXPOSURE=4.0

if ! command -v systemd-analyze >/dev/null; then
    if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
        echo "check-systemd: systemd-analyze missing, installing Debian's systemd package"
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq >/dev/null
        apt-get install -y -qq --no-install-recommends systemd >/dev/null
    fi
fi
if ! command -v systemd-analyze >/dev/null; then
    echo "check-systemd: SKIPPED: systemd-analyze not found and cannot be installed here" \
         "(needs root and apt-get; on Debian/Ubuntu: apt-get install systemd)" >&2
    [ "${REQUIRE_SYSTEMD_ANALYZE:-0}" = 1 ] && exit 1
    exit 0
fi
[ -f "$UNIT_FILE" ] || { echo "check-systemd: no unit file $UNIT_FILE" >&2; exit 2; }
UNIT="$(basename "$UNIT_FILE")"
echo "check-systemd: $(systemd-analyze --version | head -1)"

scratch="$(mktemp -d)"
trap 'rm -rf "$scratch"' EXIT
mkdir -p "$scratch/usr/lib/systemd" "$scratch/etc/systemd/system"
cp -r /usr/lib/systemd/system "$scratch/usr/lib/systemd/"
cp "$UNIT_FILE" "$scratch/etc/systemd/system/$UNIT"
# a stand-in executable at every absolute Exec*= path the unit names
sed -n 's/^Exec[A-Za-z]*=[-@:+!]*\(\/[^ ]*\).*/\1/p' "$UNIT_FILE" | while read -r exe; do
    mkdir -p "$scratch$(dirname "$exe")"
    printf '#!/bin/sh\nexit 0\n' > "$scratch$exe"
    chmod +x "$scratch$exe"
done

echo "== systemd-analyze verify $UNIT_FILE"
status=0
messages="$(systemd-analyze verify --root="$scratch" "$UNIT" 2>&1)" || status=$?
if [ "$status" != 0 ] || [ -n "$messages" ]; then
    echo "$messages" | sed "s|$scratch/etc/systemd/system/$UNIT|$UNIT_FILE|g" >&2
    echo "check-systemd: FAILED: systemd-analyze verify reported problems (exit $status)" >&2
    exit 1
fi
echo "verify: clean"

echo "== systemd-analyze security $UNIT_FILE"
threshold="$(awk -v m="$MAX_EXPOSURE" 'BEGIN { printf "%d", m * 10 }')"
status=0
systemd-analyze security --no-pager --offline=true --threshold="$threshold" "$UNIT_FILE" || status=$?
if [ "$status" != 0 ]; then
    echo "check-systemd: FAILED: exposure above $MAX_EXPOSURE" >&2
    exit 1
fi
echo "check-systemd: OK (exposure within $MAX_EXPOSURE)"
