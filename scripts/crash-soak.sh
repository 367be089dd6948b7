#!/usr/bin/env bash
# Crash-consistency soak test of `splatmark serve`.
#
#   bash scripts/crash-soak.sh [--binary PATH] [--kills N] [--seed S] [--keep] [--scene PLY]
#
# Starts the service on a fresh data folder and a free port, uploads scenes, enqueues watermark
# jobs and `kill -9`s the server at random moments (mid-upload, mid-claim, mid-finetune,
# mid-publish) N times (default 20), restarting it each time. Then it lets every job finish and
# checks:
#   * every accepted job (202) is `done` exactly once: one `job.enqueue` and one
#     `watermark.publish` audit row, one watermarked asset whose source is the job, and a replay
#     of its Idempotency-Key answers the same job;
#   * every upload that got a 201 still answers GET /v1/assets/{id} and serves the same bytes;
#   * no 5xx (other than 503 "busy") was ever answered, and no panic was logged;
#   * /v1/audit/verify reports the hash chain valid;
#   * after a clean stop (SIGTERM, exit 0): `PRAGMA integrity_check` is ok, no foreign key is
#     dangling, every blob the database references exists and matches its SHA-256 and size, and
#     `splatmark backup` + `splatmark restore` (which re-hash every blob and re-check the
#     integrity and the audit chain) succeed.
#
# The server runs with one CPU worker, `SPLATMARK_LEASE_SECONDS=3` (a killed job is re-queued
# within seconds, not a minute) and `SPLATMARK_MAX_ATTEMPTS=100` (each kill of a running job
# costs it an attempt; the default 3 would rightly send a job that is killed three times to the
# dead letter, which is not what this test is about). Jobs are tiny (4 orbit views of 64 px,
# 40 steps: a few seconds on a CPU), so 20 kills take about 2-3 minutes.
# Needs curl and python3 (no jq). The work folder (data dir, logs, records) is removed on
# success and kept on failure or with --keep.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN=""
KILLS=20
SEED=""
KEEP=0
SCENE=""

usage() {
  sed -n '2,4p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'
  exit "${1:-0}"
}

while [ $# -gt 0 ]; do
  case "$1" in
    --binary) BIN="${2:?--binary needs a path}"; shift 2 ;;
    --binary=*) BIN="${1#*=}"; shift ;;
    --kills) KILLS="${2:?--kills needs a number}"; shift 2 ;;
    --kills=*) KILLS="${1#*=}"; shift ;;
    --seed) SEED="${2:?--seed needs a number}"; shift 2 ;;
    --seed=*) SEED="${1#*=}"; shift ;;
    --scene) SCENE="${2:?--scene needs a path}"; shift 2 ;;
    --scene=*) SCENE="${1#*=}"; shift ;;
    --keep) KEEP=1; shift ;;
    -h|--help) usage 0 ;;
    *) echo "crash-soak: unknown argument '$1'" >&2; usage 2 ;;
  esac
done

if [ -z "$BIN" ]; then
  if [ -n "${CARGO_TARGET_DIR:-}" ]; then
    BIN="$CARGO_TARGET_DIR/debug/splatmark"
  else
    BIN="$ROOT/target/debug/splatmark"
  fi
fi
[ -x "$BIN" ] || { echo "crash-soak: no executable splatmark at $BIN (build it, or pass --binary PATH)" >&2; exit 2; }
BIN="$(cd "$(dirname "$BIN")" && pwd)/$(basename "$BIN")"
[[ "$KILLS" =~ ^[0-9]+$ ]] && [ "$KILLS" -ge 1 ] || { echo "crash-soak: --kills must be a positive integer" >&2; exit 2; }
[ -n "$SEED" ] || SEED=$(( $(date +%s) % 32768 ))
[[ "$SEED" =~ ^[0-9]+$ ]] || { echo "crash-soak: --seed must be a non-negative integer" >&2; exit 2; }
for tool in curl python3; do
  command -v "$tool" >/dev/null || { echo "crash-soak: $tool is required" >&2; exit 2; }
done
if [ -z "$SCENE" ] && [ -f "$ROOT/../shared/data/scenes/donut/fused.ply" ]; then
  SCENE="$ROOT/../shared/data/scenes/donut/fused.ply"
fi

RANDOM=$SEED
T0=$(date +%s)
WORK="$(mktemp -d "${TMPDIR:-/tmp}/splatmark-soak.XXXXXX")"
DATA="$WORK/data"
LOG="$WORK/server.log"
PY="$WORK/soak.py"
ASSETS="$WORK/assets.txt"     # id sha256 file            (uploads answered 201)
KEYS="$WORK/keys.txt"         # idempotency-key asset-id  (every watermark request sent)
JOBS="$WORK/jobs.txt"         # key job-id asset-id       (requests answered 202)
KILLLOG="$WORK/kills.txt"     # what each kill interrupted
export SOAK_ERRORS="$WORK/http-errors.txt"   # every 5xx (but 503) any client saw
mkdir -p "$WORK/up" "$WORK/req" "$WORK/scenes"
: >"$ASSETS"; : >"$KEYS"; : >"$JOBS"; : >"$KILLLOG"; : >"$SOAK_ERRORS"

SERVER_PID=""
BG_PIDS=()
RESTARTS=0
KILLED=0

cleanup() {
  local rc=$?
  set +e
  for p in ${BG_PIDS[@]+"${BG_PIDS[@]}"}; do kill -9 "$p" 2>/dev/null; done
  if [ -n "$SERVER_PID" ] && kill -0 "$SERVER_PID" 2>/dev/null; then
    kill -9 "$SERVER_PID" 2>/dev/null
    wait "$SERVER_PID" 2>/dev/null
  fi
  if [ "$rc" -ne 0 ] || [ "$KEEP" -eq 1 ]; then
    echo "crash-soak: work folder kept: $WORK (data: $DATA, server log: $LOG)" >&2
  else
    rm -rf "$WORK"
  fi
  exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

fail() {
  echo "crash-soak: FAIL (seed $SEED): $*" >&2
  exit 1
}

log() { printf '[%4ss] %s\n' "$(( $(date +%s) - T0 ))" "$*"; }

# ---------------------------------------------------------------------------------------------
# The Python helper: JSON, polling and the final checks (no jq needed).
cat >"$PY" <<'PYEOF'
import hashlib, json, os, socket, sqlite3, sys, time, urllib.error, urllib.request
from datetime import datetime, timezone

FINAL = ("done", "dead", "cancelled")


def note_error(msg):
    path = os.environ.get("SOAK_ERRORS")
    if path:
        with open(path, "a") as f:
            f.write(msg + "\n")


def call(base, token, method, path, body=None, headers=None, timeout=30):
    h = {"Authorization": "Bearer " + token}
    data = None
    if body is not None:
        data = json.dumps(body).encode()
        h["Content-Type"] = "application/json"
    h.update(headers or {})
    req = urllib.request.Request(base + path, data=data, method=method, headers=h)
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            status, raw, hdrs = r.status, r.read(), r.headers
    except urllib.error.HTTPError as e:
        status, raw, hdrs = e.code, e.read(), e.headers
    if status >= 500 and status != 503:
        note_error(f"{method} {path} -> {status}: {raw[:300]!r}")
    return status, raw, hdrs


def get_json(base, token, path):
    s, raw, _ = call(base, token, "GET", path)
    return s, (json.loads(raw) if raw else None)


def sha256_file(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def parse_time(s):
    return datetime.strptime(s, "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=timezone.utc)


def read_rows(path):
    with open(path) as f:
        return [l.split() for l in f if l.strip()]


def jobs_of(path):
    return [r[1] for r in read_rows(path)]


def cmd_freeport():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    print(s.getsockname()[1])
    s.close()


def cmd_field(key, path=None):
    raw = open(path, "rb").read() if path else sys.stdin.buffer.read()
    try:
        v = json.loads(raw)
        for k in key.split("."):
            v = v[k]
    except Exception:
        return
    print("" if v is None else v)


def cmd_subsample(src, out_dir, count):
    """Writes `count` small INRIA PLY scenes (every 20th Gaussian of `src`, different offsets)."""
    data = open(src, "rb").read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii")
    if "binary_little_endian" not in header:
        raise SystemExit("the scene must be a binary little-endian PLY")
    lines = header.split("\n")
    n = int(next(l for l in lines if l.startswith("element vertex")).split()[2])
    props = [l for l in lines if l.startswith("property")]
    if any(not l.startswith("property float ") for l in props):
        raise SystemExit("the scene's vertex properties must all be float")
    stride = 4 * len(props)
    body = data[end:end + n * stride]
    for i in range(int(count)):
        rows = [body[j * stride:(j + 1) * stride] for j in range(i, n, 20)]
        h = header.replace(f"element vertex {n}\n", f"element vertex {len(rows)}\n")
        open(os.path.join(out_dir, f"s{i}.ply"), "wb").write(h.encode() + b"".join(rows))


def cmd_synthetic(out_dir, count):
    """Small random object scenes (when no real scene is at hand)."""
    import math, random, struct
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    for i in range(int(count)):
        rng = random.Random(1000 + i)
        n = 2000
        head = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n
        head += "".join("property float %s\n" % p for p in names) + "end_header\n"
        rows = []
        for _ in range(n):
            u, v = rng.random(), rng.random()
            th, ph = 2 * math.pi * u, math.acos(2 * v - 1)
            r = 0.5 + 0.1 * rng.random()
            x, y, z = r * math.sin(ph) * math.cos(th), r * math.sin(ph) * math.sin(th), r * math.cos(ph)
            rows.append(struct.pack("<14f", x, y, z, rng.uniform(-1, 1), rng.uniform(-1, 1),
                                    rng.uniform(-1, 1), rng.uniform(0, 3), -3.5, -3.5, -3.5,
                                    1, 0, 0, 0))
        open(os.path.join(out_dir, f"s{i}.ply"), "wb").write(head.encode() + b"".join(rows))


def cmd_sha(path):
    print(sha256_file(path))


def cmd_wait_live(base, token, jobs_file, since, timeout, mode):
    """Waits for a job that this server instance runs (claimed after `since`); mode `any`, or
    `finetune` (in the finetuning phase with an ETA). Prints `id phase step total ms` (ms: the
    estimated milliseconds to the end of its finetuning); exit 3 on timeout."""
    deadline = time.time() + float(timeout)
    while time.time() < deadline:
        for jid in jobs_of(jobs_file):
            s, j = get_json(base, token, f"/v1/jobs/{jid}")
            if s != 200:
                raise SystemExit(f"GET /v1/jobs/{jid} answered {s}")
            if j["state"] != "running" or (j.get("heartbeat_at") or "") < since:
                continue
            if mode == "finetune" and not (j.get("phase") == "finetune" and j.get("eta_seconds") is not None):
                continue
            remaining = 0
            if j.get("eta_seconds") is not None:
                age = (datetime.now(timezone.utc) - parse_time(j["heartbeat_at"])).total_seconds()
                remaining = max(0, int(1000 * (j["eta_seconds"] - age)))
            print(jid, j.get("phase"), j["step"], j["total"], remaining)
            return 0
        time.sleep(0.1)
    return 3


def cmd_kill_at_publish(base, token, jid, pid, lead_ms, jitter_ms, timeout):
    """SIGKILLs `pid` while job `jid` publishes: polls the job (every 100 ms, every 5 ms from its
    last finetuning steps or `lead_ms` on — an ETA taken early under load can be far off either
    way) and kills `jitter_ms` after it first shows the final progress (phase "publish", the step
    after the last heartbeat: the result is being committed and published) or is done already
    (late). Prints what it saw."""
    import signal
    t0 = time.time()
    deadline = t0 + float(timeout)
    seen = "timeout"
    while time.time() < deadline:
        s, j = get_json(base, token, f"/v1/jobs/{jid}")
        if s != 200:
            raise SystemExit(f"GET /v1/jobs/{jid} answered {s}")
        if j["state"] == "running" and j.get("phase") == "publish":
            seen = "publishing"
            break
        if j["state"] != "running":
            seen = "already-" + j["state"]
            break
        near = (j.get("step") or 0) + 3 >= (j.get("total") or 0)
        soon = time.time() - t0 >= max(0, int(lead_ms)) / 1000
        time.sleep(0.005 if near or soon else 0.1)
    time.sleep(int(jitter_ms) / 1000)
    os.kill(int(pid), signal.SIGKILL)
    print(seen)


def cmd_nonfinal(base, token, jobs_file):
    n = 0
    for jid in jobs_of(jobs_file):
        s, j = get_json(base, token, f"/v1/jobs/{jid}")
        if s != 200:
            raise SystemExit(f"GET /v1/jobs/{jid} answered {s}")
        n += j["state"] not in FINAL
    print(n)


def cmd_state(base, token, jid):
    s, j = get_json(base, token, f"/v1/jobs/{jid}")
    print(j["state"] if s == 200 else f"http-{s}")


def cmd_drain(base, token, jobs_file, timeout):
    deadline = time.time() + float(timeout)
    while True:
        states = {}
        for jid in jobs_of(jobs_file):
            s, j = get_json(base, token, f"/v1/jobs/{jid}")
            if s != 200:
                raise SystemExit(f"GET /v1/jobs/{jid} answered {s}")
            states[jid] = j
        left = [j for j in states.values() if j["state"] not in FINAL]
        if not left:
            counts = {}
            for j in states.values():
                counts[j["state"]] = counts.get(j["state"], 0) + 1
            print(json.dumps(counts, sort_keys=True))
            return 0
        if time.time() > deadline:
            for j in left:
                print(f"job {j['id']} still {j['state']} (phase {j.get('phase')}, attempts "
                      f"{j['attempts']}, error {j.get('error')!r})")
            return 3
        time.sleep(0.5)


def audit_rows(base, token):
    rows, cursor = [], None
    while True:
        q = "/v1/audit?limit=1000" + (f"&cursor={cursor}" if cursor is not None else "")
        s, page = get_json(base, token, q)
        if s != 200:
            raise SystemExit(f"GET {q} answered {s}")
        rows += page["items"]
        cursor = page.get("next_cursor")
        if cursor is None:
            return rows


def cmd_check_api(base, token, assets_file, jobs_file, job_body, out_file):
    bad = []
    assets = read_rows(assets_file)
    jobs = read_rows(jobs_file)
    body = json.loads(job_body)
    for aid, sha, path in assets:
        s, a = get_json(base, token, f"/v1/assets/{aid}")
        if s != 200:
            bad.append(f"upload {aid} ({path}) got a 201 but GET /v1/assets/{aid} answers {s}")
            continue
        if a["sha256"] != sha:
            bad.append(f"asset {aid}: sha256 {a['sha256']} but the uploaded file hashes to {sha}")
        s, raw, _ = call(base, token, "GET", f"/v1/assets/{aid}/file")
        if s != 200 or hashlib.sha256(raw).hexdigest() != sha:
            bad.append(f"asset {aid}: GET /file answered {s} with bytes that do not hash to {sha}")
    results = set()
    for key, jid, aid in jobs:
        s, j = get_json(base, token, f"/v1/jobs/{jid}")
        if s != 200:
            bad.append(f"job {jid}: GET answers {s}")
            continue
        if j["state"] != "done":
            bad.append(f"job {jid} ended {j['state']} (attempts {j['attempts']}, error {j.get('error')!r})")
            continue
        rid = j.get("result_asset_id")
        if not rid:
            bad.append(f"job {jid} is done without a result asset")
            continue
        results.add(rid)
        s, r = get_json(base, token, f"/v1/assets/{rid}")
        if s != 200:
            bad.append(f"job {jid}: its result asset {rid} answers {s}")
            continue
        if r["kind"] != "watermarked" or r["source_job_id"] != jid or r["parent_id"] != aid:
            bad.append(f"job {jid}: result {rid} is kind {r['kind']}, source job "
                       f"{r['source_job_id']}, parent {r['parent_id']} (expected watermarked, {jid}, {aid})")
        s, raw, _ = call(base, token, "GET", f"/v1/assets/{rid}/file")
        if s != 200 or hashlib.sha256(raw).hexdigest() != r["sha256"]:
            bad.append(f"job {jid}: the result file does not hash to {r['sha256']} (status {s})")
        # The same request again must answer the same job (enqueued exactly once).
        s, raw, h = call(base, token, "POST", f"/v1/assets/{aid}/watermark", body,
                         {"Idempotency-Key": key})
        again = json.loads(raw) if raw else {}
        if s != 202 or again.get("id") != jid or h.get("idempotent-replayed") != "true":
            bad.append(f"job {jid}: replaying Idempotency-Key {key} answered {s} "
                       f"job {again.get('id')} replayed={h.get('idempotent-replayed')}")
    rows = audit_rows(base, token)
    per = {}
    for r in rows:
        k = (r["action"], r.get("job_id") or r.get("asset_id"))
        per[k] = per.get(k, 0) + 1
    job_ids = {jid for _, jid, _ in jobs}
    for _, jid, _ in jobs:
        for action in ("job.enqueue", "watermark.publish"):
            n = per.get((action, jid), 0)
            if n != 1:
                bad.append(f"job {jid}: {n} '{action}' audit rows (expected exactly 1)")
    for r in rows:
        if r["action"] in ("job.enqueue", "watermark.publish") and r.get("job_id") not in job_ids:
            bad.append(f"audit row {r['id']}: {r['action']} of job {r.get('job_id')} that no client was answered for")
    for aid, _, _ in assets:
        n = sum(1 for r in rows if r["action"] == "asset.upload" and r.get("asset_id") == aid)
        if n != 1:
            bad.append(f"asset {aid}: {n} 'asset.upload' audit rows (expected 1)")
    s, chain = get_json(base, token, "/v1/audit/verify")
    if s != 200 or not chain.get("ok") or chain.get("first_bad_id") is not None:
        bad.append(f"/v1/audit/verify answered {s}: {chain}")
    s, raw, _ = call(base, token, "GET", "/metrics")
    for line in raw.decode().splitlines():
        if line.startswith('splatmark_http_responses_total{class="5xx"}') and float(line.split()[-1]) != 0:
            bad.append(f"the final server instance answered 5xx: {line}")
    actions = {}
    for r in rows:
        actions[r["action"]] = actions.get(r["action"], 0) + 1
    summary = {"audit_rows": len(rows), "chain_ok": bool(chain and chain.get("ok")),
               "audit_head": (chain or {}).get("head_hash"), "actions": actions,
               "results": len(results)}
    with open(out_file, "w") as f:
        json.dump(summary, f)
    print(json.dumps(summary, sort_keys=True))
    for b in bad:
        print("CHECK FAILED: " + b, file=sys.stderr)
    return 1 if bad else 0


def cmd_check_db(data_dir, assets_file, jobs_file):
    bad = []
    db = sqlite3.connect(os.path.join(data_dir, "splatmark.db"))
    integrity = [r[0] for r in db.execute("PRAGMA integrity_check")]
    if integrity != ["ok"]:
        bad.append(f"PRAGMA integrity_check: {integrity}")
    fk = db.execute("PRAGMA foreign_key_check").fetchall()
    if fk:
        bad.append(f"PRAGMA foreign_key_check: {fk[:10]}")
    blobs = {}
    for aid, sha, size, cams in db.execute("SELECT id, sha256, size, cameras_sha256 FROM assets"):
        blobs.setdefault(sha, []).append((aid, size))
        if cams:
            blobs.setdefault(cams, []).append((aid, None))
    root = os.path.join(data_dir, "blobs")
    for sha, refs in sorted(blobs.items()):
        p = os.path.join(root, sha[:2], sha[2:])
        if not os.path.isfile(p):
            bad.append(f"blob {sha} referenced by {[a for a, _ in refs]} is missing")
            continue
        got = sha256_file(p)
        if got != sha:
            bad.append(f"blob {sha} hashes to {got}")
        size = os.path.getsize(p)
        for aid, want in refs:
            if want is not None and want != size:
                bad.append(f"asset {aid}: size {want} but its blob has {size} bytes")
    recorded_jobs = {jid: aid for _, jid, aid in read_rows(jobs_file)}
    db_jobs = {r[0]: r for r in db.execute(
        "SELECT id, asset_id, state, result_asset_id, attempts FROM jobs")}
    for jid in set(db_jobs) - set(recorded_jobs):
        bad.append(f"job {jid} is in the database but no client was answered for it")
    for jid in set(recorded_jobs) - set(db_jobs):
        bad.append(f"job {jid} was accepted (202) but is not in the database")
    for jid, (_, aid, state, rid, _) in db_jobs.items():
        if state != "done" or not rid:
            bad.append(f"job {jid} is {state} (result {rid}) in the database")
    marked = db.execute(
        "SELECT id, source_job_id, parent_id FROM assets WHERE kind = 'watermarked'").fetchall()
    sources = [s for _, s, _ in marked]
    if len(sources) != len(set(sources)):
        bad.append("two watermarked assets share a source job")
    for aid, src, parent in marked:
        j = db_jobs.get(src)
        if j is None or j[3] != aid or j[1] != parent:
            bad.append(f"watermarked asset {aid} (job {src}, parent {parent}) is not its job's result")
    originals = {r[0] for r in db.execute("SELECT id FROM assets WHERE kind = 'original'")}
    recorded = {r[0] for r in read_rows(assets_file)}
    for aid in recorded - originals:
        bad.append(f"upload {aid} got a 201 but is not in the database")
    tmp = os.path.join(root, "tmp")
    leftovers = len(os.listdir(tmp)) if os.path.isdir(tmp) else 0
    files = sum(len(fs) for d, _, fs in os.walk(root) if not d.startswith(tmp))
    attempts = sum(j[4] for j in db_jobs.values())
    summary = {"integrity": integrity[0] if integrity else None, "blobs_verified": len(blobs),
               "blob_files": files, "tmp_leftovers": leftovers,
               "unacknowledged_uploads": len(originals - recorded),
               "jobs": len(db_jobs), "attempts": attempts}
    print(json.dumps(summary, sort_keys=True))
    for b in bad:
        print("CHECK FAILED: " + b, file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    cmd, args = sys.argv[1].replace("-", "_"), sys.argv[2:]
    rc = globals()["cmd_" + cmd](*args)
    sys.exit(rc or 0)
PYEOF

py() { python3 "$PY" "$@"; }

# ---------------------------------------------------------------------------------------------
# Scenes: small subsets of the donut (or synthetic objects); several, so that uploads differ,
# and picked at random, so that some upload the same bytes again (one blob, two assets).
NSCENES=4
if [ -n "$SCENE" ]; then
  py subsample "$SCENE" "$WORK/scenes" "$NSCENES" || fail "cannot make small scenes from $SCENE"
else
  py synthetic "$WORK/scenes" "$NSCENES"
fi
SCENE_SHA=()
for i in $(seq 0 $((NSCENES - 1))); do SCENE_SHA+=("$(py sha "$WORK/scenes/s$i.ply")"); done

JOB_BODY='{"bits":32,"options":{"orbit":{"count":4,"width":64,"height":64},"holdout_every":0,"embed":{"finetune":{"steps":40,"extra_steps":0}}}}'

PORT="$(py freeport)"
BASE="http://127.0.0.1:$PORT"
OWNER=""

# Random helpers that run in this shell (a $(...) subshell would not advance $RANDOM).
rnd() { R=$(( RANDOM % $1 )); }
sleep_ms() { sleep "$(printf '%d.%03d' $(( $1 / 1000 )) $(( $1 % 1000 )))"; }

# Unrelated SPLATMARK_* settings of the caller (a config file, a master key) stay out of it.
while read -r v; do
  [ "$v" = SPLATMARK_LOG ] || unset "$v"
done < <(compgen -e | grep '^SPLATMARK_' || true)
export SPLATMARK_LEASE_SECONDS=3 SPLATMARK_MAX_ATTEMPTS=100

start_server() {
  START_ISO="$(date -u +%Y-%m-%dT%H:%M:%S.%3NZ)"
  echo "=== start $RESTARTS at $START_ISO" >>"$LOG"
  nice -n 10 "$BIN" serve --bind "127.0.0.1:$PORT" --data-dir "$DATA" --workers 1 --device cpu \
    --log-json >>"$LOG" 2>&1 &
  SERVER_PID=$!
  local i
  for i in $(seq 1 300); do
    if ! kill -0 "$SERVER_PID" 2>/dev/null; then
      wait "$SERVER_PID" 2>/dev/null || true
      SERVER_PID=""
      fail "the server exited during start $RESTARTS (after $KILLED kills); see $LOG"
    fi
    if [ "$(curl -s -o /dev/null -w '%{http_code}' --max-time 2 "$BASE/readyz" || true)" = 200 ]; then
      RESTARTS=$((RESTARTS + 1))
      return 0
    fi
    sleep 0.1
  done
  fail "the server did not become ready within 30 s (start $RESTARTS); see $LOG"
}

KILLED_BY_HELPER=0
kill_server() {
  if [ "$KILLED_BY_HELPER" -eq 1 ]; then
    KILLED_BY_HELPER=0
  elif ! kill -0 "$SERVER_PID" 2>/dev/null; then
    rc=0; wait "$SERVER_PID" || rc=$?
    SERVER_PID=""
    fail "the server died on its own (status $rc) before kill $((KILLED + 1)); see $LOG"
  else
    kill -9 "$SERVER_PID"
  fi
  wait "$SERVER_PID" 2>/dev/null || true
  SERVER_PID=""
  KILLED=$((KILLED + 1))
}

# An HTTP status that is a server error the service must not answer (503 "busy" is allowed).
check_status() { # code what
  if [ "$1" -ge 500 ] 2>/dev/null && [ "$1" != 503 ]; then
    echo "$2 -> $1" >>"$SOAK_ERRORS"
  fi
}

# POST /v1/assets/{asset}/watermark with Idempotency-Key `key`; records the job on a 202.
# Sets CODE. Runs in the foreground unless `bg` is given (then the caller collects it).
N_REQ=0
enqueue() { # key asset [bg]
  local key=$1 asset=$2 out="$WORK/req/$1.json"
  if [ "${3:-}" = bg ]; then
    ( code=$(curl -s -o "$out" -w '%{http_code}' --max-time 30 -H "Authorization: Bearer $OWNER" \
        -H 'content-type: application/json' -H "Idempotency-Key: $key" -d "$JOB_BODY" \
        "$BASE/v1/assets/$asset/watermark" || true)
      echo "$code" >"$out.code" ) &
    BG_PIDS+=($!)
    return 0
  fi
  CODE=$(curl -s -o "$out" -w '%{http_code}' --max-time 30 -H "Authorization: Bearer $OWNER" \
    -H 'content-type: application/json' -H "Idempotency-Key: $key" -d "$JOB_BODY" \
    "$BASE/v1/assets/$asset/watermark" || true)
  echo "$CODE" >"$out.code"
  record_job "$key" "$asset"
}

record_job() { # key asset: reads req/key.json(.code)
  local key=$1 asset=$2 out="$WORK/req/$1.json" code jid
  code=$(cat "$out.code" 2>/dev/null || echo 000)
  check_status "$code" "POST /v1/assets/$asset/watermark (key $key)"
  if [ "$code" = 202 ] || [ "$code" = 201 ]; then
    jid=$(py field id "$out")
    [ -n "$jid" ] || fail "watermark request $key answered $code without a job id: $(cat "$out")"
    if grep -q " $jid " "$JOBS"; then
      grep -q "^$key $jid " "$JOBS" || fail "job $jid answered for two different idempotency keys"
    else
      if grep -q "^$key " "$JOBS"; then
        fail "idempotency key $key answered two different jobs ($jid and $(grep "^$key " "$JOBS" | cut -d' ' -f2))"
      fi
      echo "$key $jid $asset" >>"$JOBS"
    fi
  fi
}

new_job() { # [bg]: a watermark request with a new idempotency key on a random uploaded asset
  local n asset
  n=$(wc -l <"$ASSETS")
  rnd "$n"
  asset=$(sed -n "$((R + 1))p" "$ASSETS" | cut -d' ' -f1)
  N_REQ=$((N_REQ + 1))
  LAST_KEY="soak-$SEED-$N_REQ"
  echo "$LAST_KEY $asset" >>"$KEYS"
  enqueue "$LAST_KEY" "$asset" "${1:-}"
}

# Requests whose answer a kill swallowed are sent again with the same key: the service must
# answer the job it queued, or queue it now (never two).
retry_pending() {
  local key asset
  while read -r key asset; do
    if grep -q "^$key " "$JOBS"; then continue; fi
    enqueue "$key" "$asset"
    [ "$CODE" = 202 ] || fail "retrying watermark request $key after a restart answered $CODE: $(cat "$WORK/req/$key.json")"
  done <"$KEYS"
}

N_UP=0
upload_bg() { # scene-index rate
  local i=$1 rate=$2 tag
  N_UP=$((N_UP + 1)); tag="u$N_UP"
  echo "$i" >"$WORK/up/$tag.scene"
  ( code=$(curl -s -o "$WORK/up/$tag.json" -w '%{http_code}' --max-time 60 ${rate:+--limit-rate "$rate"} \
      -H "Authorization: Bearer $OWNER" -F "scene=@$WORK/scenes/s$i.ply" "$BASE/v1/assets" || true)
    echo "$code" >"$WORK/up/$tag.code" ) &
  BG_PIDS+=($!)
}

upload_fg() { # scene-index
  upload_bg "$1" ""
  wait "${BG_PIDS[-1]}" || true
  collect
}

# Waits for the background requests and records what they were answered.
collect() {
  local p f tag code id sha i key asset
  for p in ${BG_PIDS[@]+"${BG_PIDS[@]}"}; do wait "$p" 2>/dev/null || true; done
  BG_PIDS=()
  for f in "$WORK"/up/*.code; do
    [ -e "$f" ] || continue
    tag=$(basename "$f" .code); code=$(cat "$f"); i=$(cat "$WORK/up/$tag.scene")
    check_status "$code" "POST /v1/assets ($tag)"
    if [ "$code" = 201 ]; then
      id=$(py field id "$WORK/up/$tag.json"); sha=$(py field sha256 "$WORK/up/$tag.json")
      [ -n "$id" ] || fail "upload $tag answered 201 without an id"
      [ "$sha" = "${SCENE_SHA[$i]}" ] || fail "upload $tag: the service says sha256 $sha, the file hashes to ${SCENE_SHA[$i]}"
      echo "$id $sha $WORK/scenes/s$i.ply" >>"$ASSETS"
      UP_OK=$((UP_OK + 1))
    else
      UP_LOST=$((UP_LOST + 1))
    fi
    mv "$f" "$f.done"
  done
  while read -r key asset; do
    if [ -e "$WORK/req/$key.json.code" ] && ! grep -q "^$key " "$JOBS"; then
      record_job "$key" "$asset"
    fi
  done <"$KEYS"
  return 0
}

# At least one job for this instance to run.
ensure_work() {
  local n
  n=$(py nonfinal "$BASE" "$OWNER" "$JOBS")
  if [ "$n" -eq 0 ]; then
    new_job
    [ "$CODE" = 202 ] || fail "watermark request $LAST_KEY answered $CODE: $(cat "$WORK/req/$LAST_KEY.json")"
  fi
}

# ---------------------------------------------------------------------------------------------
log "seed $SEED, $KILLS kills, binary $BIN, work folder $WORK, port $PORT"
UP_OK=0; UP_LOST=0
start_server
[ -s "$DATA/admin.token" ] || fail "the first start wrote no $DATA/admin.token"
ADMIN=$(tr -d '[:space:]' <"$DATA/admin.token")
curl -s -o "$WORK/owner.json" -w '%{http_code}' -H "Authorization: Bearer $ADMIN" \
  -H 'content-type: application/json' -d '{"name":"soak","scopes":["owner","verifier","auditor"]}' \
  "$BASE/v1/keys" >"$WORK/owner.code" || true
[ "$(cat "$WORK/owner.code")" = 201 ] || fail "POST /v1/keys answered $(cat "$WORK/owner.code"): $(cat "$WORK/owner.json")"
OWNER=$(py field token "$WORK/owner.json")
upload_fg 0
upload_fg 1
[ "$UP_OK" -eq 2 ] || fail "the first uploads failed: $(cat "$WORK"/up/*.json)"
new_job
[ "$CODE" = 202 ] || fail "the first watermark request answered $CODE: $(cat "$WORK/req/$LAST_KEY.json")"

# The kinds of moment, each about as often, in a seeded random order.
KINDS=(upload claim finetune publish)
PLAN=()
for i in $(seq 0 $((KILLS - 1))); do PLAN+=("${KINDS[$((i % 4))]}"); done
for ((i = KILLS - 1; i > 0; i--)); do
  rnd $((i + 1)); t=${PLAN[$i]}; PLAN[$i]=${PLAN[$R]}; PLAN[$R]=$t
done

declare -A HITS=([upload]=0 [claim]=0 [finetune]=0 [publish]=0)
PREV_JOB=""; PREV_KIND=""
for k in $(seq 1 "$KILLS"); do
  kind=${PLAN[$((k - 1))]}
  what=""
  case "$kind" in
    upload)
      # One or two uploads in flight, some throttled so that the kill lands mid-body.
      rnd 2; n=$((R + 1))
      for _ in $(seq 1 "$n"); do
        rnd "$NSCENES"; s=$R
        rnd 4; rates=("" 64k 128k 256k); rate=${rates[$R]}
        upload_bg "$s" "$rate"
      done
      rnd 1500; d=$R
      sleep_ms "$d"
      what="$n upload(s), kill after ${d} ms"
      ;;
    claim)
      # A watermark request in flight, or just answered while the worker claims it.
      new_job bg
      rnd 400; d=$R
      sleep_ms "$d"
      what="enqueue $LAST_KEY, kill after ${d} ms"
      ;;
    finetune|publish)
      ensure_work
      if job=$(py wait-live "$BASE" "$OWNER" "$JOBS" "$START_ISO" 30 finetune); then
        read -r jid phase step total rem <<<"$job"
        PREV_JOB=$jid
        if [ "$kind" = finetune ]; then
          rnd $(( rem * 8 / 10 + 1 )); d=$R
          what="job $jid ($phase $step/$total, ~${rem} ms of finetuning left), kill after ${d} ms"
          sleep_ms "$d"
        else
          # When the job shows its final progress: the worker is committing the result blob and
          # publishing it (or, when the kill comes late, has just published).
          rnd 40; d=$R
          seen=$(py kill-at-publish "$BASE" "$OWNER" "$jid" "$SERVER_PID" $(( rem - 1000 )) "$d" $(( rem / 1000 + 20 )))
          KILLED_BY_HELPER=1
          what="job $jid ($phase $step/$total, ~${rem} ms of finetuning left), polled to the end: $seen, killed ${d} ms later"
        fi
      else
        what="no job reached finetuning in this instance within 30 s; killed anyway"
      fi
      ;;
  esac
  kill_server
  HITS[$kind]=$((HITS[$kind] + 1))
  collect
  start_server
  # Whether the kill landed before or after the publish commit: the job's state now.
  if [ -n "$PREV_JOB" ]; then
    what="$what; after restart: $(py state "$BASE" "$OWNER" "$PREV_JOB")"
  fi
  PREV_JOB=""
  echo "kill $k [$kind] $what" >>"$KILLLOG"
  log "kill $k/$KILLS [$kind] $what"
  retry_pending
done

# ---------------------------------------------------------------------------------------------
log "kills done; waiting for every job to finish"
NJOBS=$(wc -l <"$JOBS")
if ! drained=$(py drain "$BASE" "$OWNER" "$JOBS" $(( 60 + 15 * NJOBS ))); then
  fail "not every job reached a final state: $drained"
fi
log "jobs: $drained"
py check-api "$BASE" "$OWNER" "$ASSETS" "$JOBS" "$JOB_BODY" "$WORK/api.json" >"$WORK/api.out" 2>"$WORK/api.err" \
  || fail "API checks failed:
$(cat "$WORK/api.err")"
log "api: $(cat "$WORK/api.out")"
if [ -s "$SOAK_ERRORS" ]; then
  fail "the service answered server errors:
$(cat "$SOAK_ERRORS")"
fi

# A clean stop: SIGTERM, exit status 0.
kill -TERM "$SERVER_PID"
for _ in $(seq 1 300); do kill -0 "$SERVER_PID" 2>/dev/null || break; sleep 0.1; done
if kill -0 "$SERVER_PID" 2>/dev/null; then fail "the server did not stop within 30 s of SIGTERM"; fi
rc=0; wait "$SERVER_PID" || rc=$?
SERVER_PID=""
[ "$rc" -eq 0 ] || fail "the server exited with status $rc after SIGTERM; see $LOG"
if grep -q 'panicked' "$LOG"; then fail "the server log shows a panic: $(grep -m3 'panicked' "$LOG")"; fi

py check-db "$DATA" "$ASSETS" "$JOBS" >"$WORK/db.out" 2>"$WORK/db.err" \
  || fail "database checks failed:
$(cat "$WORK/db.err")"
log "db: $(cat "$WORK/db.out")"

# The service's own whole-data check: a backup re-hashes every referenced blob; restoring it
# into a fresh folder re-checks the files, the integrity and the audit chain.
"$BIN" backup --out "$WORK/backup" --data-dir "$DATA" >"$WORK/backup.json" 2>"$WORK/backup.err" \
  || fail "splatmark backup failed: $(cat "$WORK/backup.err")"
mkdir -p "$WORK/restore"
cp "$DATA/master.key" "$WORK/restore/master.key"
"$BIN" restore --from "$WORK/backup" --data-dir "$WORK/restore" >"$WORK/restore.json" 2>"$WORK/restore.err" \
  || fail "splatmark restore failed: $(cat "$WORK/restore.err") $(cat "$WORK/restore.json")"
[ "$(py field ok "$WORK/restore.json")" = True ] || fail "the restored data does not verify: $(cat "$WORK/restore.json")"
head_api=$(py field audit_head "$WORK/api.json"); head_backup=$(py field audit_head "$WORK/backup.json")
[ "$head_api" = "$head_backup" ] || fail "the audit head changed after the jobs finished: $head_api (API) vs $head_backup (backup)"

ERRORS_LOGGED=$(grep -c '"level":"ERROR"' "$LOG" || true)
ELAPSED=$(( $(date +%s) - T0 ))
echo "crash-soak: OK seed=$SEED kills=$KILLED (upload ${HITS[upload]}, claim ${HITS[claim]}, finetune ${HITS[finetune]}, publish ${HITS[publish]}) restarts=$RESTARTS uploads_ok=$UP_OK (201, all kept; $UP_LOST interrupted, $(py field unacknowledged_uploads <"$WORK/db.out") of those committed anyway) jobs_ok=$NJOBS/$NJOBS (done exactly once; $(py field attempts <"$WORK/db.out") attempts) audit_rows=$(py field audit_rows "$WORK/api.json") chain=ok integrity=ok blobs_verified=$(py field blobs_verified <"$WORK/db.out") error_log_lines=$ERRORS_LOGGED elapsed=${ELAPSED}s"
