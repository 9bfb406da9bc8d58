#!/usr/bin/env bash
# Set up .venv/ in the repository root: CPU torch 2.13.0 first (a plain `torch` requirement would
# pull a multi-GB CUDA build), then radfield itself in editable mode with its test extras.
# A torch already in .venv (say, your own CUDA build) is kept. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip show torch >/dev/null 2>&1 || .venv/bin/python -m pip install --quiet torch==2.13.0
.venv/bin/python -m pip install --quiet -e '.[test]'
