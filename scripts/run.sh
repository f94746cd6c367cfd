#!/usr/bin/env bash
# One entry point for a fresh machine: checks the system, builds .venv, then runs
#   bash scripts/run.sh demo [mi-bivariate demo options]   the main demo
#   bash scripts/run.sh test [pytest options]              the test suite
#   bash scripts/run.sh setup                              only the set-up
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="${MI_BIVARIATE_VENV:-$ROOT/.venv}"
MIN_LLVM=17

say() { printf '[mi-bivariate setup] %s\n' "$*" >&2; }
die() { printf '[mi-bivariate setup] ERROR: %s\n' "$*" >&2; exit 1; }

as_root() {
    if [ "$(id -u)" = 0 ]; then "$@"
    elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then sudo "$@"
    else return 1; fi
}

apt_install() {
    command -v apt-get >/dev/null 2>&1 || return 1
    as_root env DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null || return 1
    as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
}

# Highest libLLVM major version the dynamic loader (or DRJIT_LIBLLVM_PATH) can see.
llvm_version() {
    if [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -f "$DRJIT_LIBLLVM_PATH" ]; then
        basename "$DRJIT_LIBLLVM_PATH" | grep -oE 'LLVM[-.]?[0-9]+' | grep -oE '[0-9]+' | head -n1 && return
    fi
    {
        ldconfig -p 2>/dev/null | grep -oE 'libLLVM[-.]?[0-9]+' || true
        ls /usr/lib/llvm-*/lib/libLLVM*.so* /usr/lib/*/libLLVM*.so* 2>/dev/null | grep -oE 'libLLVM[-.]?[0-9]+' || true
    } | grep -oE '[0-9]+$' | sort -n | tail -n1
}

check_llvm() {
    [ "$(uname -s)" = Linux ] || return 0   # Dr.Jit finds LLVM itself elsewhere (e.g. Homebrew on macOS)
    local v; v="$(llvm_version)"
    if [ -n "$v" ] && [ "$v" -ge "$MIN_LLVM" ]; then return 0; fi
    say "Dr.Jit's LLVM backend needs libLLVM >= $MIN_LLVM (found: ${v:-none}); older ones crash with 'Cannot select ... fminimum'."
    local pkg
    for pkg in libllvm19 libllvm18 libllvm17; do
        if command -v apt-cache >/dev/null 2>&1 && apt-cache show "$pkg" >/dev/null 2>&1 || [ "$pkg" = libllvm19 ]; then
            say "installing $pkg ..."
            if apt_install "$pkg"; then
                v="$(llvm_version)"
                [ -n "$v" ] && [ "$v" -ge "$MIN_LLVM" ] && { say "libLLVM $v installed"; return 0; }
            fi
        fi
    done
    die "no libLLVM >= $MIN_LLVM and it could not be installed automatically. On Debian/Ubuntu run 'sudo apt-get install libllvm19' (bookworm has it), or install LLVM >= $MIN_LLVM another way and set DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so; then run this command again."
}

check_python() {
    PYTHON="${PYTHON:-$(command -v python3 || true)}"
    if [ -z "$PYTHON" ]; then
        apt_install python3 python3-venv python3-pip || die "python3 (>= 3.9) is missing: install it (Debian: 'sudo apt-get install python3 python3-venv') and run this command again."
        PYTHON="$(command -v python3)"
    fi
    "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 9))' || die "python >= 3.9 is needed, $("$PYTHON" --version) found"
    if ! "$PYTHON" -c 'import venv, ensurepip' >/dev/null 2>&1; then
        local ver; ver="$("$PYTHON" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')"
        apt_install "python$ver-venv" || apt_install python3-venv || die "the python venv module is missing: 'sudo apt-get install python3-venv', then run this command again."
    fi
}

setup_venv() {
    local stamp="$VENV/.mi_bivariate-installed"
    local want; want="$(cat pyproject.toml | sha1sum | cut -d' ' -f1)"
    if [ -x "$VENV/bin/python" ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then return 0; fi
    [ -x "$VENV/bin/python" ] || { say "creating $VENV"; "$PYTHON" -m venv "$VENV"; }
    say "installing mi_bivariate and its dependencies into $VENV (first time: a few minutes)"
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q -e ".[test]"
    echo "$want" > "$stamp"
}

check_python
check_llvm
setup_venv
export PATH="$VENV/bin:$PATH"
if [ -z "${MI_BIVARIATE_DATA:-}" ] && [ -d "$ROOT/../shared/data" ]; then
    export MI_BIVARIATE_DATA="$(cd "$ROOT/../shared/data" && pwd)"
fi

cmd="${1:-help}"; shift || true
case "$cmd" in
    demo)  exec "$VENV/bin/mi-bivariate" demo "$@" ;;
    test)  exec "$VENV/bin/python" -m pytest "$@" ;;
    setup) say "ready: $VENV"; "$VENV/bin/mi-bivariate" info ;;
    *)     echo "usage: bash scripts/run.sh {demo|test|setup} [args...]"; exit 2 ;;
esac
