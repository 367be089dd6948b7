#!/usr/bin/env bash
# The GPU path on a machine with a GPU, in two halves:
#
#   bash scripts/gpu-bench.sh build   # here (the Rust machine): release binary, render
#                                     # benchmark binary, the donut scene and the Vulkan
#                                     # loaders, all into .gpubench/ (git-ignored)
#   bash scripts/gpu-bench.sh run     # there (no Rust toolchain; the device tool carries
#                                     # .gpubench): one table, in under 5 minutes
#
# `run` prints the render benchmark (CPU reference against the GPU path: forward, and
# forward + backward, for 10k / 100k / 1M Gaussians at 800×800 and donut / plant) and one
# donut embedding (32 bits, the service's defaults) on the GPU and on the CPU, with its last
# step's bit accuracy and PSNR. With the device tool:
#
#   run(command="bash scripts/gpu-bench.sh run", carry=[".gpubench"], timeout_s=420)
#
# PROFILE=dev uses the dev build instead of the release build, and DRY=1 makes `run` tiny (the
# 10k benchmark row, a 3-step embedding at 128²): a dry run of the mechanics here on Mesa's
# lavapipe is `PROFILE=dev bash scripts/gpu-bench.sh build && DRY=1 bash scripts/gpu-bench.sh run`.
set -euo pipefail
cd "$(dirname "$0")/.."
dir=.gpubench
case "${1:-}" in
build)
  profile="${PROFILE:-release}"
  rm -rf "$dir" && mkdir -p "$dir/deb"
  if [ "$profile" = release ]; then
    cargo build --release --bin splatmark
    bench=$(cargo bench --bench render --no-run --message-format=json 2>/dev/null |
      python3 -c 'import sys,json
for l in sys.stdin:
    m=json.loads(l)
    if m.get("reason")=="compiler-artifact" and m["target"]["name"]=="render" and m.get("executable"): print(m["executable"])')
    cp target/release/splatmark "$dir/"
  else
    cargo build --bin splatmark
    bench=$(cargo bench --profile dev --bench render --no-run --message-format=json 2>/dev/null |
      python3 -c 'import sys,json
for l in sys.stdin:
    m=json.loads(l)
    if m.get("reason")=="compiler-artifact" and m["target"]["name"]=="render" and m.get("executable"): print(m["executable"])')
    cp "${CARGO_TARGET_DIR:-target}/debug/splatmark" "$dir/"
  fi
  cp "$bench" "$dir/render-bench"
  # What travels is at most 64 MiB: strip and compress (the binary embeds the decoders).
  for b in splatmark render-bench; do
    strip "$dir/$b" && gzip -9 "$dir/$b"
  done
  # The shared scenes the benchmark and the embedding use (`run` points SPLATMARK_SCENES here).
  for f in donut/fused.ply plant/plant.splat; do
    src="../shared/data/scenes/$f"
    if [ -f "$src" ]; then
      mkdir -p "$dir/scenes/$(dirname "$f")" && cp "$src" "$dir/scenes/$f"
    else
      echo "gpu-bench: $src is missing; its rows will be skipped" >&2
    fi
  done
  # The Vulkan and EGL loaders the GPU machine may lack (amd64 packages).
  o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
  mkdir -p /tmp/amd64/partial
  # shellcheck disable=SC2086
  if apt-get $o update -qq >/dev/null 2>&1; then
    # shellcheck disable=SC2086
    (cd "$dir/deb" && apt-get $o download libvulkan1 libegl1 libglvnd0 >/dev/null)
  else
    echo "gpu-bench: apt-get cannot fetch the Vulkan loader here; relying on the GPU machine's" >&2
  fi
  du -sh "$dir"
  ;;
run)
  [ -f "$dir/splatmark.gz" ] || [ -x "$dir/splatmark" ] ||
    { echo "gpu-bench: run 'bash scripts/gpu-bench.sh build' first" >&2; exit 1; }
  for b in splatmark render-bench; do
    if [ -f "$dir/$b.gz" ]; then gunzip -c "$dir/$b.gz" >"$dir/$b" && chmod +x "$dir/$b"; fi
  done
  if ! ldconfig -p 2>/dev/null | grep -q libvulkan; then
    for f in "$dir"/deb/*.deb; do [ -f "$f" ] && dpkg -x "$f" /; done
    ldconfig 2>/dev/null || true
  fi
  if [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ]; then
    export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
  fi
  export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$(mktemp -d)}"
  out="${OUT:-$(mktemp -d)}"
  echo "## GPU path: $(date -u +%FT%TZ), $(nproc) CPU cores"
  command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  echo
  echo "### Render benchmark (median of 3)"
  filter=()
  extra=()
  if [ "${DRY:-0}" = 1 ]; then
    filter=(10k)
    extra=(--steps 3 --width 128 --height 128)
  fi
  SPLATMARK_SCENES="$PWD/$dir/scenes" timeout 240 "$dir/render-bench" --quick "${filter[@]}" 2>&1 |
    tee "$out/render-bench.md" || echo "(render benchmark stopped: see above)"
  echo
  echo "### Donut embedding, 32 bits, the CLI's defaults (the service's: 48 orbit views at 512²)"
  echo
  echo "Finetuning's steps by part (s, summed; report timings.steps): where a step's time goes."
  echo
  echo "| device | seconds | bits on the last step's views | PSNR (last step) | finetuning s | render | watermark | visual | backward | update | on the device |"
  echo "|---|---|---|---|---|---|---|---|---|---|---|"
  for device in wgpu cpu; do
    [ -f "$dir/scenes/donut/fused.ply" ] || break
    t0=$(date +%s.%N)
    if timeout 200 "$dir/splatmark" embed "$dir/scenes/donut/fused.ply" --device "$device" \
      --message 0123abcd "${extra[@]}" --out "$out/donut-$device.ply" >"$out/donut-$device.json" 2>"$out/donut-$device.log"; then
      t1=$(date +%s.%N)
      python3 - "$out/donut-$device.json" "$device" "$t0" "$t1" <<'EOF'
import json, re, sys
report = json.load(open(sys.argv[1]))
last = report.get("last_step") or {}
acc = last.get("bit_acc_clean")
psnr = last.get("psnr")
timings = report.get("timings") or {}
steps = timings.get("steps") or {}
parts = " | ".join(f"{steps[k]:.1f}" if k in steps else "?"
                   for k in ("render", "watermark", "visual", "backward", "update"))
print(f"| {sys.argv[2]} | {float(sys.argv[4]) - float(sys.argv[3]):.0f} | "
      f"{'?' if acc is None else f'{100 * acc:.1f} %'} | {'?' if psnr is None else f'{psnr:.2f} dB'} | "
      f"{timings.get('finetune', 0):.1f} | {parts} | "
      f"{'images, gradients, Adam' if steps.get('params_on_device') else 'images' if steps.get('images_on_device') else 'nothing'} |")
EOF
    else
      echo "| $device | failed or over 200 s (see donut-$device.log) | | | | | | | | | |"
      tail -3 "$out/donut-$device.log" || true
    fi
  done
  ;;
*)
  echo "usage: bash scripts/gpu-bench.sh build|run (PROFILE=dev for a dry run)" >&2
  exit 2
  ;;
esac
