#!/usr/bin/env bash
# A throwaway PostgreSQL server for precond's tests and benchmarks: Debian's `postgresql`
# package (installed with apt-get when missing), a new cluster in a temporary directory,
# listening on 127.0.0.1 at a free port, trust authentication, fsync off (test data only).
#
#   scripts/postgres.sh start DIR   # prints the admin URL (postgres://postgres@127.0.0.1:PORT/postgres)
#   scripts/postgres.sh stop DIR
#
# The server runs as the `postgres` system user when started by root (initdb refuses root).
set -euo pipefail
. "$(dirname "$0")/common.sh"

cmd="${1:-}"
dir="${2:-}"
if [ -z "$cmd" ] || [ -z "$dir" ]; then
    usage "start|stop DIR"
fi

bindir() {
    local d
    d="$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -n 1 || true)"
    if [ -z "$d" ] || [ ! -x "$d/initdb" ]; then
        return 1
    fi
    echo "$d"
}

as_owner() {
    if [ "$(id -u)" = 0 ]; then
        runuser -u postgres -- "$@"
    else
        "$@"
    fi
}

case "$cmd" in
start)
    if ! bin="$(bindir)"; then
        apt_install postgresql
        bin="$(bindir)"
    fi
    mkdir -p "$dir"
    if [ "$(id -u)" = 0 ]; then
        chown postgres: "$dir"
    fi
    port="$(free_port)"
    if ! as_owner "$bin/initdb" -D "$dir/data" -U postgres --auth=trust --encoding=UTF8 \
        --no-locale >"$dir/initdb.log" 2>&1; then
        echo "initdb failed (the server's user must reach $dir):" >&2
        cat "$dir/initdb.log" >&2
        exit 1
    fi
    as_owner "$bin/pg_ctl" -D "$dir/data" -l "$dir/server.log" -w -t 60 \
        -o "-c listen_addresses=127.0.0.1 -c port=$port -c unix_socket_directories=$dir \
            -c fsync=off -c synchronous_commit=off -c full_page_writes=off \
            -c max_connections=400 -c shared_buffers=128MB" \
        start >"$dir/pg_ctl.log" 2>&1 || {
        echo "PostgreSQL did not start:" >&2
        cat "$dir/pg_ctl.log" "$dir/server.log" >&2 || true
        exit 1
    }
    echo "postgres://postgres@127.0.0.1:$port/postgres"
    ;;
stop)
    if bin="$(bindir)" && [ -d "$dir/data" ]; then
        as_owner "$bin/pg_ctl" -D "$dir/data" -m immediate stop >/dev/null 2>&1 || true
    fi
    ;;
*)
    usage "start|stop DIR"
    ;;
esac
