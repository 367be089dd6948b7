#!/usr/bin/env bash
# Runs every test. Builds reuse $CARGO_TARGET_DIR, or /var/tmp/splatmark-target when it can be
# created (a warm folder outside the clone); a cold build works the same, only slower.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [ -z "${CARGO_TARGET_DIR:-}" ] && mkdir -p /var/tmp/splatmark-target 2>/dev/null; then
  export CARGO_TARGET_DIR=/var/tmp/splatmark-target
fi
if [ ! -d ../shared/data ]; then
  echo "NOTE: ../shared/data is missing: tests on real scenes will print SKIPPED and pass." >&2
fi
# Mesa's software Vulkan driver complains on stderr when there is no runtime directory.
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
cargo test --locked

# The store, the service and the job suites once more on PostgreSQL (issue 17): a throwaway
# server (scripts/pg-test-server.sh), one new database per test.
if pg=$(bash scripts/pg-test-server.sh start); then
  pg_dir=${pg%% *}
  trap 'bash scripts/pg-test-server.sh stop "$pg_dir"' EXIT
  echo "PostgreSQL pass: ${pg#* }" >&2
  SPLATMARK_TEST_POSTGRES=${pg#* } cargo test --locked --lib store::
  SPLATMARK_TEST_POSTGRES=${pg#* } cargo test --locked --test service --test jobs --test hostile_input \
    --test scale_out
else
  echo "SKIPPED: the PostgreSQL pass (no PostgreSQL server could start; see above)" >&2
fi
