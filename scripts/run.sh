#!/usr/bin/env bash
# Builds splatmark (release) and runs it with the given arguments.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [ -z "${CARGO_TARGET_DIR:-}" ] && mkdir -p /var/tmp/splatmark-target 2>/dev/null; then
  export CARGO_TARGET_DIR=/var/tmp/splatmark-target
fi
exec cargo run --release --locked --bin splatmark -- "$@"
