#!/usr/bin/env bash
# The numerics tests once more on the AVX2 code paths, on a CPU that has AVX-512 (CI's): what an
# AVX2-only CPU (an AMD EPYC, say) runs. Three libraries choose their code by the CPU, and each
# rounds some results to another last bit there: ATen's vectorised kernels (ATEN_CPU_CAPABILITY),
# MKL's BLAS and vector maths (MKL_ENABLE_INSTRUCTIONS: torch.log, exp and small matmuls; a float32
# gradient comparison once failed on AVX2 through it alone), oneDNN (ONEDNN_MAX_CPU_ISA). The
# fused C++ kernels follow ATen's level (core/backends/fused.py builds and caches one build per
# level). On a CPU without AVX-512 the suite already ran these paths: nothing more to do.
set -euo pipefail
cd "$(dirname "$0")/.."
level=$(.venv/bin/python -c "import torch; print(torch.backends.cpu.get_cpu_capability())")
if [ "$level" != "AVX512" ]; then
    echo "test_avx2.sh: this CPU runs the $level code paths already (the suite ran them)"
    exit 0
fi
export ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 ONEDNN_MAX_CPU_ISA=AVX2
# every comparison of a fused C++ kernel with its torch twin and of float32 with float64. Not
# tests/test_triton.py: Triton's interpreter computes with numpy, whose code none of the three
# switches selects, and its torch twins are the code these files check on AVX2 (it took 40% of this
# pass's time)
exec .venv/bin/python -m pytest -q "$@" tests/test_fused.py tests/test_fused_sh.py tests/test_fused_strategy.py \
    tests/test_backends.py tests/test_relight_fused.py tests/test_window.py tests/test_render.py \
    tests/test_cpu_paths.py
