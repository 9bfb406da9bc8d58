"""What the Triton tile kernels compile to on an H100 (sm_90), with no GPU: per kernel, ptxas's
registers and spills and the SASS instruction mix of the whole kernel (static counts, dominated by
the per-pair loop): barriers (BAR: a block-wide reduction or layout change waits on every warp),
shuffles (SHFL), atomics (RED/ATOM), memory fences (MEMBAR), transcendental units (MUFU).

    python scripts/kernel_report.py [--warps 8]

Static figures, not timings: they say where a kernel's time can go (a MEMBAR per atomic, a
barrier per pair, too many registers for a second block an SM) when no GPU is at hand to profile.
The options are the launchers' (core/backends/gpu/launch.py); the compile is
tests/test_triton.py's (Triton's front end, its PTX, the ptxas and nvdisasm its wheel ships)."""

from __future__ import annotations

import argparse
import collections
import inspect
import os
import re
import subprocess
import sys
import tempfile


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--warps", type=int, default=None, help="num_warps instead of the launchers' (8)")
    args = parser.parse_args()
    os.environ.pop("TRITON_INTERPRET", None)
    os.environ["TRITON_CACHE_DIR"] = tempfile.mkdtemp()   # a fresh compile, so that ptxas logs
    import triton
    from triton import knobs
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from radfield.core.backends.gpu import COMPILE_OPTIONS, NEURAL_BACKWARD_OPTIONS, gaussian_kernels, neural_kernels

    knobs.nvidia.dump_ptxas_log = True
    tools = os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin")

    def compiled(fn, options, **constexprs):
        names = list(inspect.signature(fn.fn).parameters)
        ints = {"height", "width", "tiles_x"}
        ints32 = {"offsets_ptr", "entries_ptr", "bounds_ptr", "last_ptr", "counts_ptr"}
        signature = {n: "constexpr" if n in constexprs else "i32" if n in ints else "*i32" if n in ints32
                     else "*fp32" for n in names}
        source = ASTSource(fn, signature, constexprs={(names.index(k),): v for k, v in constexprs.items()})
        if args.warps:
            options = {**options, "num_warps": args.warps}
        read, write = os.pipe()   # ptxas's log goes to the process's stdout: catch it
        saved = os.dup(1)
        os.dup2(write, 1)
        try:
            kernel = triton.compile(source, target=GPUTarget("cuda", 90, 32), options=options)
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(write)
        log = os.read(read, 1 << 20).decode(errors="replace")
        os.close(read)
        return kernel, log

    def row(name, kernel, log):
        registers = re.findall(r"Used (\d+) registers", log)
        spills = re.findall(r"(\d+) bytes spill stores", log)
        with tempfile.NamedTemporaryFile(suffix=".cubin") as cubin:
            cubin.write(kernel.asm["cubin"])
            cubin.flush()
            sass = subprocess.run([os.path.join(tools, "nvdisasm"), "-c", cubin.name], capture_output=True,
                                  text=True, check=True).stdout
        ops = collections.Counter(op.split(".")[0] for op in re.findall(
            r"^\s+/\*[0-9a-f]+\*/\s+(?:@!?U?P\w+\s+)?([A-Z][A-Z0-9_.]*)", sass, re.M))
        print(f"{name:30s} {registers[-1] if registers else '?':>4} {spills[-1] if spills else '?':>6} "
              f"{sum(ops.values()):6d} {ops['BAR']:4d} {ops['SHFL']:5d} "
              f"{ops['RED'] + ops['REDG'] + ops['ATOM'] + ops['ATOMG']:6d} {ops['MEMBAR']:6d} {ops['MUFU']:5d}")

    print(f"{'kernel (float32, sm_90)':30s} {'regs':>4} {'spill':>6} {'SASS':>6} {'BAR':>4} {'SHFL':>5} "
          f"{'atomic':>6} {'MEMBAR':>6} {'MUFU':>5}")
    row("gaussian_forward", *compiled(gaussian_kernels.gaussian_forward, COMPILE_OPTIONS, SIDE=16))
    row("gaussian_backward", *compiled(gaussian_kernels.gaussian_backward, COMPILE_OPTIONS, SIDE=16))
    for window in (False, True):
        label = "windowed" if window else "hard-edged"
        row(f"neural_forward {label}", *compiled(neural_kernels.neural_forward, COMPILE_OPTIONS, SIDE=16, UNITS=8,
                                                 WINDOW=window))
        row(f"neural_backward {label}", *compiled(neural_kernels.neural_backward, NEURAL_BACKWARD_OPTIONS[window],
                                                  SIDE=16, UNITS=8, WINDOW=window))


if __name__ == "__main__":
    main()
