#!/usr/bin/env bash
# The cluster profile of docker-compose.yml without Docker: a PostgreSQL server
# (scripts/postgres.sh), N precond replicas of a built binary over one database, and nginx in
# front with the same proxy settings as deploy/nginx-cluster.conf (static upstreams on
# loopback ports instead of Docker's DNS). For machines without Docker, and to try the
# deployment locally. Needs Debian's postgresql and nginx (installed with apt-get if missing).
#
#   scripts/cluster.sh start DIR [REPLICAS] [PORT]   # default 2 replicas, balancer on 8081
#   scripts/cluster.sh stop DIR
#
# PRECOND_BIN picks the binary (default target/release/precond); other PRECOND_* variables
# reach the replicas (e.g. PRECOND_TOKEN_FILE). Logs go to DIR/replica-K.log and DIR/nginx/.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/common.sh

cmd="${1:-}"
dir="${2:-}"
if [ -z "$cmd" ] || [ -z "$dir" ]; then
    usage "start DIR [REPLICAS] [PORT] | stop DIR"
fi

case "$cmd" in
start)
    replicas="${3:-2}"
    port="${4:-8081}"
    bin="${PRECOND_BIN:-target/release/precond}"
    [ -x "$bin" ] || { echo "no binary at $bin (cargo build --release)" >&2; exit 1; }
    if ! command -v nginx >/dev/null && [ ! -x /usr/sbin/nginx ]; then
        apt_install nginx
    fi
    mkdir -p "$dir"
    # PostgreSQL runs as its own user, which must reach its directory inside this one.
    chmod 755 "$dir"
    admin="$(scripts/postgres.sh start "$dir/postgres")"
    db="${admin%/*}/precond"
    psql "$admin" -qc "CREATE DATABASE precond" >/dev/null
    upstreams=""
    for k in $(seq 1 "$replicas"); do
        p="$(free_port)"
        PRECOND_ADDR="127.0.0.1:$p" PRECOND_DATABASE_URL="$db" PRECOND_LOG_FORMAT=json \
            nohup "$bin" serve >"$dir/replica-$k.log" 2>&1 &
        echo $! >"$dir/replica-$k.pid"
        upstreams="$upstreams    server 127.0.0.1:$p max_fails=1 fail_timeout=10s;"$'\n'
        for _ in $(seq 1 100); do
            curl -fsS "http://127.0.0.1:$p/healthz" >/dev/null 2>&1 && break
            sleep 0.1
        done
    done
    mkdir -p "$dir/nginx"
    # The proxy settings of deploy/nginx-cluster.conf; only the upstreams differ.
    location="$(sed -n '/^    location \/ {/,/^    }/p' deploy/nginx-cluster.conf)"
    cat >"$dir/nginx/nginx.conf" <<EOF
pid $dir/nginx/nginx.pid;
error_log $dir/nginx/error.log;
events { worker_connections 1024; }
http {
    access_log off;
    client_body_temp_path $dir/nginx/body;
    proxy_temp_path $dir/nginx/proxy;
    upstream precond {
$upstreams        keepalive 32;
    }
    server {
        listen 127.0.0.1:$port;
        client_max_body_size 64m;
$location
    }
}
EOF
    nginx -c "$dir/nginx/nginx.conf"
    for _ in $(seq 1 50); do
        curl -fsS "http://127.0.0.1:$port/healthz" >/dev/null 2>&1 && break
        sleep 0.1
    done
    echo "balancer http://127.0.0.1:$port  ($replicas replicas over $db)"
    ;;
stop)
    [ -f "$dir/nginx/nginx.pid" ] && kill "$(cat "$dir/nginx/nginx.pid")" 2>/dev/null || true
    for f in "$dir"/replica-*.pid; do
        [ -f "$f" ] && kill "$(cat "$f")" 2>/dev/null || true
    done
    scripts/postgres.sh stop "$dir/postgres"
    ;;
*)
    usage "start DIR [REPLICAS] [PORT] | stop DIR"
    ;;
esac
