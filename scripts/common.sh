# shellcheck shell=bash
# What the scripts under scripts/ share; sourced by them, not run.

# usage SYNOPSIS: says how to call the script (on stderr) and exits 2.
usage() {
    echo "usage: $0 $1" >&2
    exit 2
}

# free_port: a TCP port on 127.0.0.1 that nothing listens on.
free_port() {
    python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
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
