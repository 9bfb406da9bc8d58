"""The switches that make an AVX-512 CPU run the AVX2 code paths (scripts/test_avx2.sh, run by CI
after the suite) do change what runs: otherwise that second pass would prove nothing. Each check
runs in a fresh interpreter, since the libraries read the variables when they load."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

AVX2 = {"ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2", "ONEDNN_MAX_CPU_ISA": "AVX2"}

# the SIMD level torch picks, the fused kernels' build name and flags, and the bits of torch.log of
# fixed float32 numbers (MKL's vector maths: its AVX2 and AVX-512 code round some to another last bit)
PROBE = """
import json, torch
from radfield.core.backends import fused
x = torch.linspace(0.01, 50.0, 100_003, dtype=torch.float32)
print(json.dumps({"level": torch.backends.cpu.get_cpu_capability(), "build": fused._build_name(),
                  "flags": fused._simd_flags(), "log": torch.log(x).view(torch.int32).tolist()}))
"""


def probe(switches: dict[str, str]) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in AVX2} | switches
    done = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_the_avx2_switches_change_the_code_that_runs():
    native, avx2 = probe({}), probe(AVX2)
    assert avx2["level"] == "AVX2" and avx2["build"] == "radfield_kernels_avx2"
    assert "-mavx2" in avx2["flags"] and not any("avx512" in flag for flag in avx2["flags"])
    if native["level"] != "AVX512":
        pytest.skip(f"this CPU's own level is {native['level']}: the suite itself runs the AVX2 paths")
    assert native["build"] == "radfield_kernels_avx512" and "-mavx512f" in native["flags"]
    # MKL's AVX2 code really runs: some logarithms come out a last bit apart (4 % of these)
    differ = sum(a != b for a, b in zip(native["log"], avx2["log"]))
    assert differ > 0, "MKL_ENABLE_INSTRUCTIONS=AVX2 changed no result of torch.log"
