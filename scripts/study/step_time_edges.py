"""ms per training step at render.supersample 1 and 2, alternating in one process (two rounds), for
the trained primitives of a neural and a Gaussian run of the same scene (densification off), on the
run's training views: what supersampling costs a step.
    usage: OMP_NUM_THREADS=1 .venv/bin/python scripts/study/step_time_edges.py NEURAL_RUN GAUSSIAN_RUN [STEPS]"""
import sys
import time

from radfield.model_file import load_model
from radfield.core.trainer.loop import train
from radfield.datasets.scene import load_scene
from radfield.pipeline.config import load_config
from radfield.stages.train import to_normalized

runs, steps = sys.argv[1:3], int(sys.argv[3]) if len(sys.argv) > 3 else 150
for run in runs:
    config = load_config(f"{run}/config.yaml")
    scene = load_scene(f"{run}/data/scene.json")
    norm = scene.normalization
    cameras = [norm.camera(c) for c in scene.train_cameras]
    images, _ = scene.load_images("train")
    prims = to_normalized(load_model(f"{run}/train/model.safetensors"), norm)
    times = {1: [], 2: []}
    for _ in range(2):
        for n in (1, 2):
            cfg = {**config["train"], "iterations": steps, "supersample": n, "eval_every": 0}
            cfg["densify"] = {**cfg["densify"], "start": 10**9, "stop": 10**9}
            start = time.perf_counter()
            train(prims, cameras, images, cfg, background=scene.background, extent=scene.extent * norm.scale,
                  seed=0, near=config["render"]["near"] * norm.scale)
            times[n].append((time.perf_counter() - start) / steps * 1e3)
    print(f"{run}: {prims.kind}, {len(prims)} primitives, ms per step at n = 1: "
          + " / ".join(f"{t:.1f}" for t in times[1]) + ", n = 2: " + " / ".join(f"{t:.1f}" for t in times[2])
          + " (the first includes loading the kernels)")
