#!/usr/bin/env bash
# Load test of `splatmark serve` with wrk (Debian's `wrk`; scripts/setup.sh does not install it:
# `apt-get install wrk`).
#
#   bash scripts/load-test.sh [--binary PATH] [--connections 100] [--duration 60] [--scene PLY]
#                             [--database-url postgres://…]
#
# Starts the service on a fresh data folder (one CPU worker), uploads a scene, runs one small
# watermarking job to the end (its result gives the attribution pages and the verification
# target), then enqueues a default job and, while that job's worker finetunes, drives each
# endpoint in turn with `--connections` clients for `--duration` seconds:
#   GET /healthz · GET /v1/assets/{id} · GET /v1/assets/{result}/attribution?limit=100 ·
#   POST /v1/verify (one 256² PNG render of the result, multipart) ·
#   POST /v1/assets/{id}/watermark (enqueue: a job row and an audit row per request)
# and prints, per endpoint, requests/s and latency p50 / p90 / p99 (wrk --latency), the status
# classes the server counted (/metrics before and after), and how many finetuning steps the
# worker made during the phase (a starved worker would make none). Fails when any phase saw a
# 5xx other than 503 (the verifier's "busy, retry" answer) or the worker made no progress.
# The rate limits are raised for the run (verify_per_minute, auth_failures_per_minute) so that
# the figures measure the service, not its limiter. The store is SQLite in the data folder, or
# the (empty) database `--database-url` names, e.g. one from scripts/pg-test-server.sh.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN=""
CONNS=100
DURATION=60
SCENE=""
DATABASE_URL=""
while [ $# -gt 0 ]; do
  case "$1" in
    --binary) BIN="${2:?}"; shift 2 ;;
    --connections) CONNS="${2:?}"; shift 2 ;;
    --duration) DURATION="${2:?}"; shift 2 ;;
    --scene) SCENE="${2:?}"; shift 2 ;;
    --database-url) DATABASE_URL="${2:?}"; shift 2 ;;
    -h|--help) sed -n '2,5p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "load-test: unknown argument '$1'" >&2; exit 2 ;;
  esac
done
if [ -z "$BIN" ]; then
  BIN="${CARGO_TARGET_DIR:-$ROOT/target}/debug/splatmark"
fi
[ -x "$BIN" ] || { echo "load-test: no executable splatmark at $BIN (build it, or pass --binary)" >&2; exit 2; }
for tool in wrk curl python3; do
  command -v "$tool" >/dev/null || { echo "load-test: $tool is required" >&2; exit 2; }
done
[ -n "$SCENE" ] || SCENE="$ROOT/../shared/data/scenes/donut/fused.ply"
[ -f "$SCENE" ] || { echo "load-test: no scene at $SCENE (pass --scene)" >&2; exit 2; }

WORK="$(mktemp -d "${TMPDIR:-/tmp}/splatmark-load.XXXXXX")"
SERVER_PID=""
cleanup() {
  local rc=$?
  set +e
  if [ -n "$SERVER_PID" ]; then kill "$SERVER_PID" 2>/dev/null; wait "$SERVER_PID" 2>/dev/null; fi
  if [ "$rc" -eq 0 ]; then rm -rf "$WORK"; else echo "load-test: work folder kept: $WORK" >&2; fi
  exit "$rc"
}
trap cleanup EXIT
fail() { echo "load-test: FAIL: $*" >&2; exit 1; }
field() { python3 -c 'import json,sys; v=json.load(sys.stdin)
for k in sys.argv[1].split("."): v=v[k]
print(v)' "$1"; }

PORT=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
BASE="http://127.0.0.1:$PORT"
cat >"$WORK/load.toml" <<EOF
verify_per_minute = 1000000000
auth_failures_per_minute = 1000000000
EOF
while read -r v; do [ "$v" = SPLATMARK_LOG ] || unset "$v"; done < <(compgen -e | grep '^SPLATMARK_' || true)
[ -z "$DATABASE_URL" ] || export SPLATMARK_DATABASE_URL="$DATABASE_URL"
"$BIN" serve --config "$WORK/load.toml" --bind "127.0.0.1:$PORT" --data-dir "$WORK/data" \
  --workers 1 --device cpu >"$WORK/server.log" 2>&1 &
SERVER_PID=$!
for _ in $(seq 1 300); do
  [ "$(curl -s -o /dev/null -w '%{http_code}' "$BASE/readyz" || true)" = 200 ] && break
  sleep 0.1
done
ADMIN=$(tr -d '[:space:]' <"$WORK/data/admin.token")
TOKEN=$(curl -sf -H "Authorization: Bearer $ADMIN" -H 'content-type: application/json' \
  -d '{"name":"load","scopes":["owner","verifier","auditor"]}' "$BASE/v1/keys" | field token)
AUTH="Authorization: Bearer $TOKEN"
ASSET=$(curl -sf -H "$AUTH" -F "scene=@$SCENE" "$BASE/v1/assets" | field id)

wait_job() { # job-id timeout-s
  local s
  for _ in $(seq 1 $(( $2 * 2 ))); do
    s=$(curl -sf -H "$AUTH" "$BASE/v1/jobs/$1" | field state)
    case "$s" in done) return 0 ;; dead|cancelled) fail "job $1 ended $s" ;; esac
    sleep 0.5
  done
  fail "job $1 not done within $2 s"
}
job_step() { curl -sf -H "$AUTH" "$BASE/v1/jobs/$1" | field step; }

# A small job first: its result is what the attribution and verification phases read.
SMALL='{"bits":32,"options":{"orbit":{"count":4,"width":64,"height":64},"holdout_every":0,"embed":{"finetune":{"steps":40,"extra_steps":0}}}}'
J1=$(curl -sf -H "$AUTH" -H 'content-type: application/json' -H 'Idempotency-Key: small' \
  -d "$SMALL" "$BASE/v1/assets/$ASSET/watermark" | field id)
wait_job "$J1" 900
RESULT=$(curl -sf -H "$AUTH" "$BASE/v1/jobs/$J1" | field result_asset_id)
curl -sf -H "$AUTH" -o "$WORK/result.ply" "$BASE/v1/assets/$RESULT/file"
"$BIN" render "$WORK/result.ply" --orbit 1 --width 256 --height 256 --out "$WORK/render" >/dev/null
PNG=$(ls "$WORK"/render/*.png | head -1)

# The job that runs during the load: the service's defaults.
J2=$(curl -sf -H "$AUTH" -H 'content-type: application/json' -H 'Idempotency-Key: busy' \
  -d '{"bits":32}' "$BASE/v1/assets/$ASSET/watermark" | field id)
for _ in $(seq 1 1200); do
  ph=$(curl -sf -H "$AUTH" "$BASE/v1/jobs/$J2" | field phase)
  [ "$ph" = finetune ] && break
  sleep 0.5
done
[ "$ph" = finetune ] || fail "the default job did not reach finetuning within 10 minutes"

# wrk's Lua scripts.
cat >"$WORK/get.lua" <<EOF
wrk.headers["Authorization"] = "Bearer $TOKEN"
EOF
python3 - "$PNG" "$RESULT" "$TOKEN" >"$WORK/verify.lua" <<'PYEOF'
import sys
png, asset, token = sys.argv[1], sys.argv[2], sys.argv[3]
print('local f = io.open("%s", "rb"); local png = f:read("*a"); f:close()' % png)
print('local b = "splatmarkloadboundary"')
print('wrk.method = "POST"')
print('wrk.headers["Authorization"] = "Bearer %s"' % token)
print('wrk.headers["Content-Type"] = "multipart/form-data; boundary=" .. b')
print('wrk.body = "--" .. b .. "\\r\\nContent-Disposition: form-data; name=\\"asset_id\\"\\r\\n\\r\\n%s\\r\\n"' % asset
      + ' .. "--" .. b .. "\\r\\nContent-Disposition: form-data; name=\\"image\\"; filename=\\"v.png\\"\\r\\nContent-Type: image/png\\r\\n\\r\\n"'
      + ' .. png .. "\\r\\n--" .. b .. "--\\r\\n"')
PYEOF
cat >"$WORK/enqueue.lua" <<EOF
wrk.method = "POST"
wrk.headers["Authorization"] = "Bearer $TOKEN"
wrk.headers["Content-Type"] = "application/json"
wrk.body = '{"bits":32}'
EOF
# Every response's status, counted per thread and summed at the end.
cat >"$WORK/count.lua" <<'EOF'
local threads = {}
function setup(thread) table.insert(threads, thread) end
function init(args) codes = {} end
function response(status, headers, body) codes[status] = (codes[status] or 0) + 1 end
function done(summary, latency, requests)
  local total = {}
  for _, t in ipairs(threads) do
    for k, v in pairs(t:get("codes")) do total[k] = (total[k] or 0) + v end
  end
  for k, v in pairs(total) do io.write(string.format("status %d %d\n", k, v)) end
end
EOF
cat "$WORK/count.lua" >>"$WORK/get.lua"
cat "$WORK/count.lua" >>"$WORK/verify.lua"
cat "$WORK/count.lua" >>"$WORK/enqueue.lua"

STORE=SQLite; [ -z "$DATABASE_URL" ] || STORE=PostgreSQL
echo "load-test: $CONNS connections × ${DURATION}s per endpoint, server 127.0.0.1:$PORT ($STORE; 1 CPU worker finetuning job $J2), $(nproc) cores"
printf '| endpoint | requests/s | p50 ms | p90 ms | p99 ms | responses by status | worker steps during the phase |\n|---|---|---|---|---|---|---|\n' >"$WORK/table.md"
BAD=0
for phase in "GET /healthz|$BASE/healthz|get" "GET /v1/assets/{id}|$BASE/v1/assets/$ASSET|get" \
             "GET /v1/assets/{id}/attribution|$BASE/v1/assets/$RESULT/attribution?limit=100|get" \
             "POST /v1/verify (one 256² PNG)|$BASE/v1/verify|verify" \
             "POST /v1/assets/{id}/watermark (enqueue)|$BASE/v1/assets/$ASSET/watermark|enqueue"; do
  IFS='|' read -r name url script <<<"$phase"
  s0=$(job_step "$J2")
  wrk -t2 -c"$CONNS" -d"${DURATION}s" --timeout 30s --latency -s "$WORK/$script.lua" "$url" >"$WORK/wrk.out" 2>&1 || true
  s1=$(job_step "$J2")
  state=$(curl -sf -H "$AUTH" "$BASE/v1/jobs/$J2" | field state)
  row=$(python3 - "$WORK/wrk.out" <<'PYEOF'
import re, sys
out = open(sys.argv[1]).read()
def ms(label):
    m = re.search(r'^\s*%s%%\s+([\d.]+)(us|ms|s)\b' % label, out, re.M)
    if not m: return float('nan')
    v, u = float(m.group(1)), m.group(2)
    return v / 1000 if u == 'us' else v * 1000 if u == 's' else v
rps = re.search(r'Requests/sec:\s+([\d.]+)', out)
codes = {int(c): int(n) for c, n in re.findall(r'^status (\d+) (\d+)$', out, re.M)}
cls = ', '.join(f'{c}: {n}' for c, n in sorted(codes.items()))
bad = sum(n for c, n in codes.items() if c >= 500 and c != 503)
print(f"{float(rps.group(1)) if rps else float('nan'):.0f}|{ms('50'):.1f}|{ms('90'):.1f}|{ms('99'):.1f}|{cls}|{bad}")
PYEOF
)
  IFS='|' read -r rps p50 p90 p99 cls n5 <<<"$row"
  if [ "$state" = done ]; then steps="$((s1 - s0)) (job done)"; else steps="$((s1 - s0))"; fi
  echo "| $name | $rps | $p50 | $p90 | $p99 | $cls | $steps |" >>"$WORK/table.md"
  echo "  $name: $rps req/s, p50 $p50 ms, p99 $p99 ms; $cls; worker +$steps steps"
  grep -q "Socket errors" "$WORK/wrk.out" && echo "    wrk: $(grep 'Socket errors' "$WORK/wrk.out")"
  # 503 is the verifier's bounded queue answering "busy" with Retry-After; any other 5xx fails.
  [ "${n5:-0}" -eq 0 ] || BAD=1
  if [ "$state" != done ] && [ "$((s1 - s0))" -le 0 ]; then fail "the worker made no progress during $name"; fi
done
echo
cat "$WORK/table.md"
[ "$BAD" -eq 0 ] || fail "server errors (5xx other than 503) were answered"
echo "load-test: OK"
