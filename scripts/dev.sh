#!/usr/bin/env bash
# One entry point for a fresh machine. Each sub-command sets up what it needs first:
# system library libusb-1.0-0 (open3d-cpu), chromium for the browser test (setup, test), a virtual environment in .venv, the package
# with torch pinned to the CPU build (override with OPENFUSION_TORCH_SPEC, e.g. "torch" for CUDA).
#
#   scripts/dev.sh run  [openfusion run options]   # the embedded default: all services, synthetic scene
#   scripts/dev.sh test [pytest options]           # the fast test suite (add -m slow for the slow one)
#   scripts/dev.sh bench [bench options]           # the benchmark suite (bench/run_all.py)
#   scripts/dev.sh setup                           # only set up
#   scripts/dev.sh exec CMD ...                    # run CMD inside the environment
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${OPENFUSION_VENV:-$root/.venv}"
torch_spec="${OPENFUSION_TORCH_SPEC:-torch==2.13.0}"
extras="${OPENFUSION_EXTRAS:-test,viz}"

log() { printf '[dev.sh] %s\n' "$*" >&2; }

ensure_libusb() {
    if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
        return
    fi
    log "installing system library libusb-1.0-0 (needed by open3d-cpu)"
    local sudo=""
    if [ "$(id -u)" != "0" ]; then
        if command -v sudo >/dev/null 2>&1; then sudo="sudo"; else
            log "ERROR: libusb-1.0-0 is missing and this user cannot install it; run: apt-get install -y libusb-1.0-0"
            exit 1
        fi
    fi
    $sudo apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq libusb-1.0-0 >/dev/null
}

# The browser test of the query page (tests/process/test_web_page.py) drives Debian's chromium
# through Playwright (Playwright's own browser download is not used). Without it that test fails
# in CI (CI=true) naming what is missing, and is skipped elsewhere.
ensure_chromium() {
    if [ -x /usr/bin/chromium ]; then
        return
    fi
    log "installing chromium (for the browser test of the query page)"
    local sudo=""
    if [ "$(id -u)" != "0" ]; then
        if command -v sudo >/dev/null 2>&1; then sudo="sudo"; else
            log "WARNING: chromium is missing and this user cannot install it; run: apt-get install -y chromium"
            return
        fi
    fi
    { $sudo apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq chromium >/dev/null; } ||
        log "WARNING: could not install chromium with apt; the browser test will say so"
}

ensure_venv() {
    local stamp="$venv/.openfusion-stamp"
    local want
    want="$(cat "$root/pyproject.toml" "$root/scripts/dev.sh" | sha256sum | cut -c1-16) $torch_spec $extras"
    if [ -x "$venv/bin/python" ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
        return
    fi
    local py="${PYTHON:-python3}"
    "$py" -c 'import sys; assert sys.version_info >= (3, 11), "Python >= 3.11 needed"' || {
        log "ERROR: $py is older than Python 3.11"; exit 1; }
    log "creating virtual environment in $venv (first run takes a few minutes)"
    "$py" -m venv "$venv"
    "$venv/bin/python" -m pip install -q --upgrade pip 2>&1 | grep -v '^WARNING: Location' >&2 || true
    # torch first and pinned, so no later requirement pulls a multi-GB CUDA build.
    "$venv/bin/python" -m pip install -q "$torch_spec" 2>&1 | grep -v '^WARNING: Location' >&2 || true
    "$venv/bin/python" -m pip install -q -e "$root[$extras]" 2>&1 | grep -v '^WARNING: Location' >&2 || true
    "$venv/bin/python" -c 'import openfusion, open3d, zenoh, torch' || {
        log "ERROR: the environment did not install; see the pip output above"; exit 1; }
    echo "$want" > "$stamp"
}

cmd="${1:-help}"
[ $# -gt 0 ] && shift
case "$cmd" in
    setup) ensure_libusb; ensure_chromium; ensure_venv ;;
    run) ensure_libusb; ensure_venv; exec "$venv/bin/openfusion" run "$@" ;;
    test)
        ensure_libusb; ensure_chromium; ensure_venv
        cd "$root"
        export HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1
        exec "$venv/bin/python" -m pytest "$@" ;;
    bench) ensure_libusb; ensure_venv; cd "$root"; export HF_HUB_OFFLINE=1; exec "$venv/bin/python" bench/run_all.py "$@" ;;
    exec) ensure_libusb; ensure_venv; export PATH="$venv/bin:$PATH" HF_HUB_OFFLINE=1; exec "$@" ;;
    *) sed -n '2,12p' "$0"; exit 2 ;;
esac
