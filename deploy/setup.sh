#!/usr/bin/env bash
# Creates the virtual environment and installs everything wreckmap needs:
# Debian packages from deploy/system-packages.txt (with apt-get when root,
# otherwise one line saying what to install), then the Python packages with
# all extras. Called by `make setup`; safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
VENV=${VENV:-.venv}

# A line is a package name, optionally followed by a command that, when already on PATH,
# counts as the package (NodeSource's nodejs ships npm without Debian's npm package).
mapfile -t lines < <(grep -v -E '^\s*(#|$)' deploy/system-packages.txt || true)
missing=()
for line in "${lines[@]}"; do
    read -r p command _ <<<"$line"
    if [ -n "${command:-}" ] && command -v "$command" >/dev/null; then
        continue
    fi
    dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "setup: installing system packages: ${missing[*]}"
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
    else
        echo "setup: missing system packages, install them with: sudo apt-get install ${missing[*]}" >&2
        exit 1
    fi
fi

[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -e ".[field,post,dev]"

# Some packages pull the GUI OpenCV wheel beside the headless one; both
# provide `cv2` and the last one installed wins. Keep only the headless one.
for gui in opencv-python opencv-contrib-python; do
    if "$VENV/bin/python" -m pip show -q "$gui" >/dev/null 2>&1; then
        echo "setup: removing $gui (keeping opencv-python-headless)"
        "$VENV/bin/python" -m pip uninstall -q -y "$gui"
        "$VENV/bin/python" -m pip install -q --force-reinstall --no-deps \
            "$(grep -o 'opencv-python-headless==[0-9.]*' pyproject.toml)"
    fi
done
# The 3D viewer of report.html: three.js pinned in package.json / package-lock.json,
# bundled into node_modules/.wreckmap/three-bundle.js, which the report inlines.
# (--ignore-scripts: esbuild's optional postinstall only checks its binary.)
npm ci --no-audit --no-fund --ignore-scripts --loglevel=error
npm run --silent build
echo "setup: environment ready in $VENV"
