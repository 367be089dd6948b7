#!/usr/bin/env bash
# Coverage-guided fuzzing of one of splatmark's parsers with AFL++ (cargo afl, stable toolchain).
#
#   scripts/fuzz.sh TARGET SECONDS [JOBS]     TARGET: scene cameras image job_options query text
#   scripts/fuzz.sh seeds                     rewrites fuzz/corpus/ from the seeds binary
#   scripts/fuzz.sh replay TARGET FILE...     runs a target once per file, outside AFL
#
# Builds fuzz/ (its own workspace) into $FUZZ_DIR/target (default /var/tmp/splatmark-fuzz),
# runs JOBS fuzzer processes (one main, the rest secondaries) for SECONDS, resumes a previous
# run of the same target, and prints executions, crashes and hangs. Findings stay under
# $FUZZ_DIR/out/TARGET/*/crashes|hangs; replay them, fix, and add a regression test.
# Limits per execution: 1 GiB of memory (-m 1024), 1 s (-t 1000).
set -euo pipefail
cd "$(dirname "$0")/../fuzz"
FUZZ_DIR=${FUZZ_DIR:-/var/tmp/splatmark-fuzz}
export CARGO_TARGET_DIR="$FUZZ_DIR/target"
if ! cargo afl --version >/dev/null 2>&1; then
  cargo install cargo-afl --locked --version '^0.18'
fi
if ! ls "$HOME"/.local/share/afl.rs/rustc-*/afl.rs-*/afl/bin/afl-fuzz >/dev/null 2>&1; then
  cargo afl config --build
fi
cargo afl build --release --locked --bins 2>&1 | tail -n 3
bin="$CARGO_TARGET_DIR/release"
case "${1:-}" in
  seeds)
    rm -rf corpus && "$bin/seeds" corpus
    exit 0 ;;
  replay)
    shift
    exec "$bin/replay" "$@" ;;
esac
target=${1:?usage: scripts/fuzz.sh TARGET SECONDS [JOBS]}
secs=${2:?usage: scripts/fuzz.sh TARGET SECONDS [JOBS]}
jobs=${3:-1}
[ -x "$bin/$target" ] || { echo "no fuzz target '$target'" >&2; exit 2; }
out="$FUZZ_DIR/out/$target"
export AFL_SKIP_CPUFREQ=1 AFL_NO_UI=1 AFL_I_DONT_CARE_ABOUT_MISSING_CRASHES=1 AFL_NO_AFFINITY=1
mkdir -p "$out"
pids=()
for k in $(seq 1 "$jobs"); do
  name="s$k"; [ "$k" = 1 ] && name=main
  role=(-S "$name"); [ "$k" = 1 ] && role=(-M main)
  # An instance that ran before resumes its queue; a new one starts from the seeds.
  input="corpus/$target"; [ -f "$out/$name/fuzzer_stats" ] && input=-
  cargo afl fuzz -i "$input" -o "$out" -m 1024 -t 1000 -V "$secs" "${role[@]}" "$bin/$target" \
    >"$out/log.$k" 2>&1 &
  pids+=($!)
done
status=0
for p in "${pids[@]}"; do wait "$p" || status=$?; done
execs=0; crashes=0; hangs=0
for s in "$out"/*/fuzzer_stats; do
  execs=$((execs + $(awk '/^execs_done/ {print $3}' "$s")))
  crashes=$((crashes + $(awk '/^saved_crashes/ {print $3}' "$s")))
  hangs=$((hangs + $(awk '/^saved_hangs/ {print $3}' "$s")))
done
echo "$target: $execs executions in this output folder's last runs, $crashes crashes, $hangs hangs (afl-fuzz exit $status)"
[ "$crashes" = 0 ] && [ "$hangs" = 0 ]
