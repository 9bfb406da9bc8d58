#!/usr/bin/env bash
# PlayCanvas splat-transform, the third-party reader and writer that tests/test_model_formats.py checks
# radfield's model formats against (issue 41), pinned to the last 2.x release (2.7.1: engines node >= 18;
# 3.4 and later need node 22). Installed into .splat-transform/ (git-ignored); safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
VERSION=2.7.1
DIR=.splat-transform
BIN="$DIR/node_modules/.bin/splat-transform"
if [ -x "$BIN" ] && "$BIN" --version 2>/dev/null | grep -q "v$VERSION"; then
    exit 0
fi
command -v npm >/dev/null || { echo "install_splat_transform.sh: npm is missing (apt-get install -y nodejs npm)" >&2; exit 1; }
# --ignore-scripts: the webgpu dependency's postinstall fetches GPU binaries that no conversion here uses
npm install --prefix "$DIR" --no-audit --no-fund --ignore-scripts --save-exact "@playcanvas/splat-transform@$VERSION"
"$BIN" --version
