#!/usr/bin/env bash
# A throwaway PostgreSQL server for the tests (Debian's `postgresql` package, which
# scripts/setup.sh installs): `start` initialises a cluster in a new temporary folder (byte-wise
# "C" collation, trust authentication on 127.0.0.1 only, fsync off: nothing in it outlives the
# run), starts it on a free local port and prints "FOLDER URL"; `stop FOLDER` stops it and
# removes the folder. PostgreSQL refuses to run as root: as root, the server runs as the
# `postgres` user the package creates.
set -euo pipefail
bindir=$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -1 || true)
as_owner=()
if [ "$(id -u)" -eq 0 ]; then
  as_owner=(runuser -u postgres --)
fi
case "${1:-}" in
start)
  if [ -z "$bindir" ] || [ ! -x "$bindir/initdb" ]; then
    echo "pg-test-server: no PostgreSQL server binaries under /usr/lib/postgresql" >&2
    exit 3
  fi
  dir=$(mktemp -d /tmp/splatmark-pg.XXXXXX)
  chmod 755 "$dir"
  [ ${#as_owner[@]} -gt 0 ] && chown postgres "$dir"
  port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
  if ! "${as_owner[@]}" "$bindir/initdb" -D "$dir/data" -U postgres --auth=trust --locale=C \
      -E UTF8 >"$dir/initdb.log" 2>&1; then
    echo "pg-test-server: initdb failed:" >&2
    cat "$dir/initdb.log" >&2
    exit 1
  fi
  if ! "${as_owner[@]}" "$bindir/pg_ctl" -D "$dir/data" -l "$dir/server.log" -w -t 60 \
      -o "-p $port -k $dir -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=300" \
      start >/dev/null; then
    echo "pg-test-server: the server did not start:" >&2
    cat "$dir/server.log" >&2
    exit 1
  fi
  echo "$dir postgres://postgres@127.0.0.1:$port"
  ;;
stop)
  dir="${2:?usage: pg-test-server.sh stop FOLDER}"
  "${as_owner[@]}" "$bindir/pg_ctl" -D "$dir/data" -m fast -w stop >/dev/null 2>&1 || true
  rm -rf "$dir"
  ;;
*)
  echo "usage: pg-test-server.sh start | stop FOLDER" >&2
  exit 2
  ;;
esac
