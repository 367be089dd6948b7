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

# The store, the service and the job suites once more on PostgreSQL and S3-compatible object
# storage together (issue 17): a throwaway PostgreSQL server (scripts/pg-test-server.sh, one new
# database per test) and a throwaway SeaweedFS (scripts/s3-test-server.sh, one key prefix per
# test). Whichever cannot start is skipped loudly; the pass runs on the other alone.
pass_env=()
cleanup() {
  [ -n "${pg_dir:-}" ] && bash scripts/pg-test-server.sh stop "$pg_dir"
  [ -n "${s3_dir:-}" ] && bash scripts/s3-test-server.sh stop "$s3_dir"
  return 0
}
trap cleanup EXIT
if pg=$(bash scripts/pg-test-server.sh start); then
  pg_dir=${pg%% *}
  echo "PostgreSQL for the second pass: ${pg#* }" >&2
  pass_env+=("SPLATMARK_TEST_POSTGRES=${pg#* }")
else
  echo "SKIPPED: the PostgreSQL pass (no PostgreSQL server could start; see above)" >&2
fi
if s3=$(bash scripts/s3-test-server.sh start); then
  s3_dir=${s3%% *}
  echo "S3 (SeaweedFS) for the second pass: $(echo "${s3#* }" | sed 's#//[^@]*@#//***@#')" >&2
  pass_env+=("SPLATMARK_TEST_S3=${s3#* }")
else
  echo "SKIPPED: the S3 blob pass (no S3-compatible server could start; see above)" >&2
fi
if [ ${#pass_env[@]} -gt 0 ]; then
  env "${pass_env[@]}" cargo test --locked --lib store::
  env "${pass_env[@]}" cargo test --locked --test service --test jobs --test hostile_input \
    --test scale_out --test secrets
fi
