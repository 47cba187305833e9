#!/usr/bin/env bash
# Idempotent set-up for comgs_dr on Debian/Ubuntu, then optionally run the demo or the tests.
#   bash setup.sh            # set up only
#   bash setup.sh demo       # set up if needed, then `comgs demo` (no download, writes out/demo/)
#   bash setup.sh test       # set up if needed (and Chromium), then lint-imports and the whole test suite
set -euo pipefail
cd "$(dirname "$0")"
VENV="${COMGS_VENV:-.venv}"
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"

# 1. LLVM 19 for Dr.Jit's CPU backend (Dr.Jit 1.5 refuses LLVM 14 and crashes with 15/16).
if ! ls /usr/lib/*/libLLVM.so.19* >/dev/null 2>&1 && ! ls /usr/lib/*/libLLVM-19.so >/dev/null 2>&1; then
  echo "[setup] installing libllvm19 through apt"
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq libllvm19
fi

# 2. A virtual environment with the package, the CPU build of PyTorch and the dev tools.
if [ ! -x "$VENV/bin/python" ]; then
  echo "[setup] creating $VENV"
  python3 -m venv "$VENV"
fi
stamp="$VENV/.comgs_installed"
if [ ! -f "$stamp" ] || [ setup.cfg -nt "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "[setup] pip install -e .[dev,cpu] (torch==2.13.0 CPU build)"
  "$VENV/bin/python" -m pip install -q --upgrade pip 2>&1 | grep -v "^WARNING: Location" || true
  "$VENV/bin/python" -m pip install -q "torch==2.13.0" 2>&1 | grep -v "^WARNING: Location" || true
  "$VENV/bin/python" -m pip install -q -e ".[dev,cpu]" 2>&1 | grep -v "^WARNING: Location" || true
  "$VENV/bin/python" -c "import comgs_dr, mitsuba, drjit, torch" && touch "$stamp"
fi

# 3. (tests only) Debian's Chromium for the browser test of `comgs view`
#    (tests/test_view_browser.py drives /usr/bin/chromium with playwright; no `playwright
#    install`, no download). About 100 s of apt on a clean machine; skipped once installed.
install_chromium() {
  if [ ! -x /usr/bin/chromium ]; then
    echo "[setup] installing chromium through apt (the browser test of comgs view)"
    { $SUDO apt-get update -qq &&
      $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; } ||
      echo "[setup] chromium could not be installed: tests/test_view_browser.py will skip" >&2
  fi
}

case "${1:-}" in
  demo) shift; exec "$VENV/bin/comgs" demo "$@" ;;
  test) shift; install_chromium; "$VENV/bin/lint-imports"
        export COMGS_NOTEBOOK_TINY="${COMGS_NOTEBOOK_TINY:-1}"   # notebooks at smoke-test sizes
        export PYTHONFAULTHANDLER=1   # a crash in native code prints the Python stack
        exec "$VENV/bin/python" -m pytest -q "$@" ;;
  "") echo "[setup] done. Activate with: source $VENV/bin/activate" ;;
  *) echo "usage: bash setup.sh [demo|test] [extra args]" >&2; exit 2 ;;
esac
