# shellcheck shell=bash
# What the scripts under scripts/ share; sourced by them, not run.

# usage SYNOPSIS: says how to call the script (on stderr) and exits 2.
usage() {
    echo "usage: $0 $1" >&2
    exit 2
}

# free_port: a TCP port on 127.0.0.1 that nothing is bound to, drawn below the kernel's
# ephemeral range. A port the kernel hands out for bind(0) is one it also hands to outgoing
# connections, so between choosing it and listening on it a replica's connection to PostgreSQL
# could take it (CI saw nginx fail with "Address already in use" that way); a port below
# ip_local_port_range is never given to a connection, only to a listener that asks for it.
free_port() {
    python3 - <<'PY'
import random, socket
with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
    low = int(f.read().split()[0])
for _ in range(1000):
    port = random.randrange(max(1024, low - 12000), low)
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            continue
    print(port)
    break
else:
    raise SystemExit("no free port below the ephemeral range")
PY
}

# apt_install PACKAGE: installs a Debian package missing on this machine (with sudo unless
# root). Everything apt-get says goes to stderr, so stdout stays the script's answer.
apt_install() {
    local sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    echo "== apt-get install $1 (not on this machine)" >&2
    $sudo apt-get update -qq >&2
    $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$1" >&2
}

# server_binary: exports PRECOND_BIN as an absolute path to the server binary,
# ${PRECOND_BIN:-${CARGO_TARGET_DIR:-target}/debug/precond}, building it first if missing.
server_binary() {
    local target="${CARGO_TARGET_DIR:-target}"
    PRECOND_BIN="${PRECOND_BIN:-$target/debug/precond}"
    if [ ! -x "$PRECOND_BIN" ]; then
        echo "== cargo build --locked (no server binary at $PRECOND_BIN)"
        cargo build --locked
    fi
    PRECOND_BIN="$(cd "$(dirname "$PRECOND_BIN")" && pwd)/$(basename "$PRECOND_BIN")"
    export PRECOND_BIN
}

# ensure_venv DIR: makes a Python virtual environment at DIR unless one is there.
ensure_venv() {
    if [ ! -x "$1/bin/python" ]; then
        echo "== python3 -m venv $1"
        python3 -m venv "$1"
    fi
}
