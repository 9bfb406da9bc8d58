#!/usr/bin/env bash
# The device checks of a session on a GPU machine (CONTRIBUTING.md "Device (GPU) checks"): the CUDA tests and
# every figure of issue 27, in parts that fit a short lease (15 minutes, start-up included):
#
#   scripts/gpu_check.sh                 tests, bench and e2e64 (about 7 minutes)
#   scripts/gpu_check.sh tests           the CUDA tests, the Triton kernels compiled on CUDA tensors
#   scripts/gpu_check.sh bench           the issue's table, before (the torch twins, --baseline: the
#                                        same run) and after (Triton), and its speed targets
#   scripts/gpu_check.sh e2e64           a 100-view 64x64 object scene, 3000 steps, --no-cage, on the
#                                        GPU: time and held-out PSNR (the CPU's figure, the same
#                                        method: DEVICE=cpu scripts/gpu_check.sh e2e64)
#   scripts/gpu_check.sh e2e800 [STEPS]  glossy at 800x800 (100 + 20 views), STEPS steps (default
#                                        30000) within the time left: ms per step and PSNR
#   scripts/gpu_check.sh kernels         what to tune: the launch options timed against their
#                                        alternatives (scripts/tune_kernels.py), then Nsight Compute on
#                                        the tile kernels of one 100k-primitive 800x800 forward+backward
#                                        of each kind (duration, throughput, occupancy, warp stalls)
#   scripts/gpu_check.sh sanitize        compute-sanitizer memcheck over tests/test_triton.py (renders,
#                                        gradients, statistics, loss, projection, training): reads and
#                                        writes out of bounds, which Triton's interpreter cannot see
#   DRY_RUN=1 scripts/gpu_check.sh PART  PART here, on the CPU, without the packages the GPU machine
#                                        lacks: what would fail there for a reason other than the GPU
#                                        (before a lease: `tests` takes 4 minutes, `e2e64` 2)
#
# Under the device tool ($OUT set) the whole output is also kept in $OUT/gpu_check.log, and the
# profiler's tables (where a 100k-primitive 800x800 view spends host and GPU time) go to
# $OUT/profile-100k-800.txt rather than the output.
#
# The machine has a CUDA torch and Triton but not the geometry and SfM libraries (pymeshlab,
# pyvista, pycolmap, pytetwild, fast-simplification), so everything runs `--no-cage`. Wheels it
# lacks travel in .whl/ (run(carry=[".whl"])):
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 -d .whl OpenImageIO==3.2.2.0 plyfile==1.1.5
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if compgen -G ".whl/*.whl" >/dev/null && ! $PY -c "import OpenImageIO, plyfile" 2>/dev/null; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
W=$(mktemp -d); trap 'rm -rf "$W"' EXIT
# DRY_RUN=1: a part on this machine's CPU as the GPU machine would run it, the packages that machine
# lacks (its image's list, KINDS.md of the device tool) failing to import in every Python process
MISSING=pymeshlab,pyvista,vtk,pycolmap,pytetwild,fast_simplification,viser,meshio,imageio_ffmpeg,trimesh,lpips
if [ "${DRY_RUN:-0}" = 1 ]; then
    WITHOUT=$MISSING DEVICE=${DEVICE:-cpu}
    mkdir -p "$W/without" && cat >"$W/without/sitecustomize.py" <<EOF
import importlib.abc, sys
class Missing(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in set("$WITHOUT".split(",")):
            raise ImportError(f"No module named {name!r} (gpu_check.sh WITHOUT)", name=name)
sys.meta_path.insert(0, Missing())
EOF
    export PYTHONPATH="$W/without:$PYTHONPATH"
fi
radfield() { $PY -m radfield "$@"; }
secs() { local t0; t0=$(date +%s%N); "$@"; local rc=$?; echo "  ($(( ($(date +%s%N) - t0) / 1000000 )) ms, exit $rc)"; }
CORES=$(nproc)
DEVICE=${DEVICE:-cuda}   # DEVICE=cpu runs a part on the CPU (its figures for the same-method comparisons)
scene() { $PY -c "from radfield.demo.static import generate_scene as g; g('$1', '$2', size=$3, mesh=False, workers=$CORES)"; }

summary() {   # a run's train time, steps, primitives and held-out PSNR
    radfield info "$1" --json | $PY -c "import json,sys; s=json.load(sys.stdin)['stages']; t=s['train']; \
print('  train', {k: t.get(k) for k in ('seconds', 'iterations', 'primitives')}, 'held-out psnr', s['eval'].get('psnr'))"
}

part_tests() {
    echo "== CUDA tests, the backend comparisons and the blocked-import tests"
    secs $PY -m pytest -q -rfE -p no:cacheprovider tests/test_cuda.py tests/test_backends.py tests/test_imports.py 2>&1 \
        | tail -25
    echo "== the Triton backend's kernels compiled on CUDA tensors against the torch twin (tests/test_triton.py)"
    secs env -u TRITON_INTERPRET $PY -m pytest -q -rfE -p no:cacheprovider tests/test_triton.py 2>&1 | tail -25
    echo "== a --no-cage reconstruction on the GPU, then render, eval, export"
    scene blobs "$W/blobs" 64
    secs radfield reconstruct "$W/blobs" -o "$W/run" --no-cage --device "$DEVICE" --iterations 300 -q
    summary "$W/run"
    secs radfield render "$W/run" -o "$W/frames" --device "$DEVICE" -q
    secs radfield eval "$W/run" -o "$W/report" --device "$DEVICE" -q
    secs radfield export "$W/run" -f ply-3dgs -o "$W/model.ply" --refine 20 -q
}

part_bench() {
    echo "== issue table: bench-render, 10k primitives, 256x256 (before: the torch twins, same run)"
    secs radfield bench-render --device "$DEVICE" --primitives 10000 --views 4 --repeats 3 --baseline
    echo "== issue table: kernel launches of one forward+backward, 10k primitives, 256x256 (twins, then Triton)"
    RADFIELD_KERNELS=torch radfield bench-render --device "$DEVICE" --primitives 10000 --views 1 --repeats 1 --profile \
        | grep "kernel launches"
    radfield bench-render --device "$DEVICE" --primitives 10000 --views 1 --repeats 1 --profile | grep "kernel launches"
    echo "== issue table: bench-train, neural, 10k primitives, 64 / 256 / 800 (before: the twins, same run)"
    secs radfield bench-train --device "$DEVICE" --kinds neural --primitives 10000 --sizes 64,256,800 --steps 10 --baseline -q
    echo "== targets: bench-render, 100k primitives, 800x800 (forward >= 100 FPS neural, >= 300 FPS Gaussians)"
    secs radfield bench-render --device "$DEVICE" --primitives 100000 --width 800 --height 800 --views 4 --repeats 3
    echo "== targets: bench-train, neural and Gaussians, 100k primitives, 256 / 800 (neural at 800: <= 25 ms a step)"
    secs radfield bench-train --device "$DEVICE" --kinds neural,gaussian --primitives 100000 --sizes 256,800 --steps 10 -q
    echo "== where the time goes: one forward+backward, 100k primitives, 800x800 (torch profiler, by host and device time)"
    local profile=${OUT:-$W}/profile-100k-800.txt
    radfield bench-render --device "$DEVICE" --primitives 100000 --width 800 --height 800 --views 1 --repeats 1 \
        --profile >"$profile" 2>&1
    echo "  (exit $?)"
    if [ -n "${OUT:-}" ]; then grep "kernel launches" "$profile"; echo "  (the tables: \$OUT/profile-100k-800.txt)"
    else cat "$profile"; fi
}

part_e2e64() {
    echo "== issue table: reconstruct of a 100-view 64x64 object scene (studio), 3000 steps, --no-cage, GPU"
    secs scene studio "$W/studio64" 64   # no mesh.ply: its writer needs pyvista
    secs radfield reconstruct "$W/studio64" -o "$W/studio64-run" --no-cage --device "$DEVICE" -q
    summary "$W/studio64-run"
}

part_e2e800() {
    local steps=${1:-30000}
    echo "== target: reconstruct of glossy at 800x800 (100 + 20 views), $steps steps, --no-cage, GPU (<= 10 min for 30k)"
    secs scene glossy "$W/glossy800" 800
    # in the background, its progress printed each minute: a run cut off by the call's time limit
    # still tells its ms per step
    secs radfield reconstruct "$W/glossy800" -o "$W/glossy800-run" --no-cage --device "$DEVICE" --iterations "$steps" \
        -q &
    local job=$! polls=0
    while kill -0 "$job" 2>/dev/null; do
        sleep 2; polls=$((polls + 1))
        if [ $((polls % 30)) = 0 ]; then progress "$W/glossy800-run/train/log.jsonl"; fi
    done
    wait "$job"
    summary "$W/glossy800-run"
}

progress() {   # the last record of a training log: step, seconds, ms per step
    tail -n 1 "$1" 2>/dev/null | $PY -c "import json, sys
try:
    r = json.loads(sys.stdin.read())
except ValueError:   # no log yet, or a line being written
    r = None
print('  training: not started' if r is None else
      f\"  training: step {r['step']} at {r['seconds']:.0f} s ({1e3 * r['seconds'] / r['step']:.1f} ms a step)\")"
}

part_kernels() {
    echo "== launch options against their alternatives, 100k primitives, 800x800 (scripts/tune_kernels.py)"
    secs $PY scripts/tune_kernels.py --device "$DEVICE" --primitives 100000 --size 800
    echo "== Nsight Compute: the tile kernels of one forward+backward, 100k primitives, 800x800, each kind"
    local report=${OUT:-$W}/ncu-kernels.txt
    secs ncu --clock-control none -k "regex:^(neural|gaussian)_(forward|backward)" \
        --section SpeedOfLight --section Occupancy --section LaunchStats --section WarpStateStats \
        $PY -c "import torch
from radfield.bench.render import bench_cameras, bench_models
from radfield.core.render.rasterize import render
camera = bench_cameras(1, 800, 800)[0]
for name, prims in bench_models(100000).items():
    print(name, flush=True)
    params = prims.to('cuda').map(lambda t: t.clone().requires_grad_(True))
    render(params, camera).color.sum().backward()
torch.cuda.synchronize()" >"$report" 2>&1
    grep -E "^  [a-z_]+_(forward|backward)|^[a-z-]+$|Duration|Registers Per|Achieved Occupancy|Compute \(SM\) Thr|Memory Thr" \
        "$report" | head -80
    if [ -n "${OUT:-}" ]; then echo "  (the whole report: \$OUT/ncu-kernels.txt)"; fi
}

part_sanitize() {
    echo "== compute-sanitizer memcheck: the Triton kernels of tests/test_triton.py on tiny views"
    # one cudaMalloc a tensor, so that a read or write past a tensor's end lands outside any allocation
    secs env -u TRITON_INTERPRET PYTORCH_NO_CUDA_MEMORY_CACHING=1 compute-sanitizer --tool memcheck \
        --target-processes all --print-limit 20 --error-exitcode 9 $PY -m pytest -q -x -rfE -p no:cacheprovider \
        tests/test_triton.py -k "not compile and not reads_the_device and not launches" 2>&1 \
        | tail -30
}

main() {
    if [ "$DEVICE" = cuda ]; then
        nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
        $PY -c "import torch, triton; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name(), 'triton', triton.__version__)"
    fi
    case "${1:-default}" in
        default) part_tests; part_bench; part_e2e64 ;;
        tests) part_tests ;;
        bench) part_bench ;;
        e2e64) part_e2e64 ;;
        e2e800) part_e2e800 "${2:-30000}" ;;
        kernels) part_kernels ;;
        sanitize) part_sanitize ;;
        *) echo "usage: scripts/gpu_check.sh [tests|bench|e2e64|e2e800 [STEPS]|kernels|sanitize]" >&2; exit 2 ;;
    esac
}

# on the device tool, $OUT comes back but only the last 12,000 characters of the output do: keep it all
if [ -n "${OUT:-}" ] && [ -d "$OUT" ]; then
    main "$@" 2>&1 | tee -a "$OUT/gpu_check.log"
    exit "${PIPESTATUS[0]}"
fi
main "$@"
