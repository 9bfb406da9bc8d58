#!/usr/bin/env bash
# The device checks of one session on a GPU machine (CONTRIBUTING.md "GPU checks"): the CUDA tests
# and the GPU figures, in one script that fits a short lease. The machine has a CUDA torch but not
# the geometry and SfM libraries (pymeshlab, pyvista, pycolmap, pytetwild, fast-simplification), so
# everything here runs `--no-cage`. Wheels it lacks travel in .whl/ (OpenImageIO, plyfile):
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 -d .whl OpenImageIO==3.2.2.0 plyfile==1.1.5
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if compgen -G ".whl/*.whl" >/dev/null; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
radfield() { $PY -m radfield "$@"; }
secs() { local t0; t0=$(date +%s%N); "$@"; local rc=$?; echo "  ($(( ($(date +%s%N) - t0) / 1000000 )) ms, exit $rc)"; }
OUT=${OUT:-/tmp/gpu_check}; mkdir -p "$OUT"; W=$(mktemp -d)

nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
$PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name())"
for lib in pymeshlab pyvista pycolmap pytetwild fast_simplification; do
    $PY -c "import $lib" 2>/dev/null && echo "note: $lib is installed here" || echo "no $lib here"
done

echo "== start-up (imports where they are used)"
radfield bench-startup --repeats 3 | tail -3

echo "== CUDA tests, the backend comparisons and the blocked-import tests"
secs $PY -m pytest -q -p no:cacheprovider -x tests/test_cuda.py tests/test_backends.py tests/test_imports.py 2>&1 | tail -5

echo "== a --no-cage reconstruction on the GPU, then render, eval, export (no geometry libraries)"
$PY -c "from radfield.datasets.synthetic import generate_scene; generate_scene('blobs', '$W/blobs', mesh=False)"
secs radfield reconstruct "$W/blobs" -o "$W/run" --no-cage --device cuda --iterations 300 -q
radfield info "$W/run" --json | $PY -c "import json,sys; s=json.load(sys.stdin)['stages']; print('  train', {k: s['train'].get(k) for k in ('seconds','primitives','train_psnr')}, 'eval psnr', s['eval'].get('psnr'))"
secs radfield render "$W/run" -o "$W/frames" --device cuda -q
secs radfield eval "$W/run" -o "$W/report" --device cuda -q
secs radfield export "$W/run" -f ply-3dgs -o "$W/model.ply" --refine 20 -q

echo "== the Triton backend's kernels compiled on CUDA tensors against the torch twin (tests/test_triton.py, no interpreter)"
secs env -u TRITON_INTERPRET $PY -m pytest -q -p no:cacheprovider tests/test_triton.py 2>&1 | tail -5

echo "== bench-render on the GPU (the Triton view kernels; --baseline: the torch twins in the same run)"
secs radfield bench-render --device cuda --primitives 10000 --views 4 --repeats 3 --baseline
echo "== bench-train on the GPU"
secs radfield bench-train --device cuda --primitives 10000 --sizes 64,256 --steps 5 --quiet
rm -rf "$W"
