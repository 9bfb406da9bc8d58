"""CPU milliseconds (thread CPU time, so other jobs on a shared machine inflate it less than wall
time) of the fused part of a training step outside the loss: loop.assemble + render forward +
backward (of colour.sum()) + the strategy's per-view statistics, and of the statistics alone, at
64×64 with bench-render's 10k primitives, SH degree 3; the minimum of 5 rounds of 40 steps.
Run it on two trees alternately to compare them. Usage:
    OMP_NUM_THREADS=1 .venv/bin/python scripts/step_chain.py gaussian|neural"""

import sys
import time

from radfield.bench.render import bench_cameras, bench_scene
from radfield.bench.train import bench_config
from radfield.core.trainer import loop
from radfield.core.render.rasterize import render
from radfield.core.trainer.loop import make_strategy


def main(kind: str) -> None:
    neural, gauss = bench_scene(10_000)
    prims = neural if kind == "neural" else gauss
    cams = bench_cameras(4, 64, 64)
    state = loop.initial_state(prims, 3)
    params = {n: t.clone().requires_grad_(True) for n, t in state.params.items()}
    strategy = make_strategy(kind, bench_config(30)["densify"], extent=1.0, near=0.01, max_primitives=None,
                             initial_count=len(prims))
    accumulators = strategy.init_state(len(prims), "cpu")

    def step(i: int, render_too: bool) -> None:
        if render_too:
            render(loop.assemble(params, kind, state.attrs), cams[i % 4], sh_degree=3).color.sum().backward()
        strategy.accumulate(accumulators, params, {n: params[n].grad for n in strategy.grad_names}, cams[i % 4], 1)
        if render_too:
            for p in params.values():
                p.grad = None

    def best(render_too: bool) -> float:
        rounds = []
        for _ in range(5):
            start = time.thread_time()
            for i in range(40):
                step(i, render_too)
            rounds.append(1e3 * (time.thread_time() - start) / 40)
        return min(rounds)

    step(0, True)
    chain = best(True)
    render(loop.assemble(params, kind, state.attrs), cams[0], sh_degree=3).color.sum().backward()
    print(f"{kind}: assemble + render forward + backward + statistics {chain:.2f} ms, statistics alone "
          f"{best(False):.3f} ms (CPU time per step)")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "gaussian")
