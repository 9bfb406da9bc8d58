"""Time the Triton tile kernels' launch options against their alternatives on one GPU, in one run:
launch.py's choices (8 warps, one thread a pixel; the hard-edged neural backward capped at 160
registers, the windowed one left at ptxas's 214) were made from static figures
(scripts/kernel_report.py), with no GPU to time them. Each row times bench-render's scene (its
models and orbit cameras, radfield.bench.render.time_model): every kind's forward and
forward+backward, and the largest difference of its image from the shipped options' (launch options
must not change a render).

    python scripts/tune_kernels.py [--primitives 100000] [--size 800] [--repeats 5]

A study: for each row it rewrites the launchers' option dicts (core/backends/gpu/launch.py) in
place, which nothing in the product does. Without a GPU it runs the kernels in Triton's interpreter
on CPU tensors (--device cpu, tiny sizes): that checks the script, not the options, which the
interpreter ignores."""

from __future__ import annotations

import argparse
import os

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--primitives", type=int, default=100_000)
    parser.add_argument("--size", type=int, default=800, help="view width and height in pixels")
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    if args.device == "cpu":
        os.environ.setdefault("TRITON_INTERPRET", "1")   # before the kernels are imported
    from radfield.bench.render import bench_cameras, bench_models, time_model
    from radfield.core import backends
    from radfield.core.backends.gpu import launch
    from radfield.core.render.rasterize import render

    shipped = (launch.COMPILE_OPTIONS["num_warps"], launch.NEURAL_BACKWARD_OPTIONS[False].get("maxnreg"),
               launch.NEURAL_BACKWARD_OPTIONS[True].get("maxnreg"))
    # (name, num_warps, the hard-edged neural backward's register cap, the windowed one's)
    variants = [("as shipped", *shipped),
                ("hard backward: ptxas's own registers", shipped[0], None, shipped[2]),
                ("hard backward <= 128 registers", shipped[0], 128, shipped[2]),
                ("windowed backward <= 128 registers", shipped[0], shipped[1], 128),
                ("windowed backward <= 168 registers", shipped[0], shipped[1], 168),
                ("4 warps (two pixels a thread)", 4, shipped[1], shipped[2])]

    def configure(num_warps: int, hard_cap: int | None, window_cap: int | None) -> None:
        launch.COMPILE_OPTIONS["num_warps"] = num_warps   # the dict the launchers pass, changed in place
        for window, cap in ((False, hard_cap), (True, window_cap)):
            launch.NEURAL_BACKWARD_OPTIONS[window] = {**launch.COMPILE_OPTIONS, **({"maxnreg": cap} if cap else {})}

    models = {name: prims.to(args.device) for name, prims in bench_models(args.primitives).items()}
    cameras = bench_cameras(args.views, args.size, args.size)
    print(f"tune_kernels: {args.primitives} primitives, {args.views} views of {args.size}x{args.size}, "
          f"{args.repeats} repeats, device={args.device}; ms per frame (backward = forward+backward - forward)")
    print(f"  {'variant':38s} {'kind':12s} {'forward':>9s} {'backward':>9s} {'fwd+bwd':>9s}  image vs shipped")
    reference = {}
    with backends.using("triton"):
        for name, *options in variants:
            configure(*options)
            for kind, prims in models.items():
                timing = time_model(prims, cameras, args.repeats, args.device)
                with torch.no_grad():
                    image = render(prims, cameras[0]).color
                difference = (image - reference.setdefault(kind, image)).abs().max().item()
                print(f"  {name:38s} {kind:12s} {timing.forward_ms:9.2f} {timing.backward_ms - timing.forward_ms:9.2f} "
                      f"{timing.backward_ms:9.2f}  {difference:.1e}", flush=True)
    configure(*shipped)


if __name__ == "__main__":
    main()
