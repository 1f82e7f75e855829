#!/usr/bin/env bash
# One-time set-up for `make demo` / `make test` on Debian 12 with Python 3.11:
# the system LLVM that Mitsuba's CPU backend needs, libusb for pyusb, and the venv.
set -euo pipefail
VENV=${VENV:-.venv}

# true if any of the glob patterns matches an existing file
any_file() {
    local pattern f
    for pattern in "$@"; do
        for f in $pattern; do
            [ -e "$f" ] && return 0
        done
    done
    return 1
}
have_llvm19() {
    any_file '/usr/lib/*/libLLVM-19.so*' '/usr/lib/*/libLLVM.so.19*' '/usr/lib/llvm-19/lib/libLLVM*.so*'
}
have_libusb() {
    any_file '/usr/lib/*/libusb-1.0.so*' '/lib/*/libusb-1.0.so*'
}

if ! have_llvm19 || ! have_libusb; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "setup: installing libllvm19 and libusb-1.0-0 with apt-get"
        DEBIAN_FRONTEND=noninteractive apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 libusb-1.0-0 >/dev/null
    else
        echo "setup: Mitsuba's CPU backend needs libLLVM 19 and pyusb needs libusb." >&2
        echo "setup: run as root:  apt-get install -y libllvm19 libusb-1.0-0   then re-run make." >&2
        exit 1
    fi
fi

PY=${PYTHON:-}
if [ -z "$PY" ]; then
    for c in python3.11 python3; do
        if command -v "$c" >/dev/null && "$c" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then PY=$c; break; fi
    done
fi
if [ -z "$PY" ]; then
    echo "setup: Python >= 3.11 not found; install it (apt-get install -y python3 python3-venv)" >&2
    exit 1
fi
if [ ! -x "$VENV/bin/python" ]; then
    if ! "$PY" -m venv "$VENV"; then
        echo "setup: '$PY -m venv' failed; install the venv module (apt-get install -y python3-venv)" >&2
        exit 1
    fi
fi
"$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
# constraints.txt pins every package to the versions the suite last passed with, so a fresh
# machine installs what was tested rather than whatever PyPI has newest that day.
"$VENV/bin/python" -m pip install -q -c constraints.txt -e '.[test]'
touch "$VENV/.installed"
echo "setup: ready ($VENV)"
