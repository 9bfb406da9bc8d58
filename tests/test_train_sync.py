"""Training without host reads inside the loop (issue 27): the steps' loss and PSNR stay on the
device and are read every `train.log_every` steps (radfield.core.trainer.loop.StepRecords), and
the log is the same whatever log_every is. CPU checks; tests/test_cuda.py has the GPU's own."""

import dataclasses
import json
import math

import pytest
import torch

from radfield.core.geometry.cameras import Camera, look_at
from radfield.core.kinds import random_gaussians, random_neural
from radfield.core.render.rasterize import render
from radfield.core.trainer import loop
from radfield.core.trainer.loop import save_checkpoint, train
from radfield.core.trainer.log import read_log
from radfield.datasets.images import write_image
from radfield.model_file import save_model
from radfield.errors import RadfieldError
from radfield.pipeline.config import load_config, load_defaults, section
from radfield.pipeline.runner import Context
from radfield.stages import train as train_stage

BG = (1.0, 1.0, 1.0)


def orbit(n: int, size: int) -> list[Camera]:
    cameras = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = (3.0 * math.cos(a), 3.0 * math.sin(a), 0.3 + 0.8 * math.sin(3 * a))
        cameras.append(Camera(fx=1.3 * size, fy=1.3 * size, cx=size / 2, cy=size / 2, width=size, height=size,
                              c2w=look_at(eye, (0, 0, 0)), name=f"view{i}"))
    return cameras


def views(n: int = 3, size: int = 16):
    cameras = orbit(n, size)
    truth = random_neural(30, extent=0.6, scale=0.25, seed=1)
    with torch.no_grad():
        return cameras, torch.stack([render(truth, c, background=BG).color.clamp(0, 1) for c in cameras])


def small_config(**changes) -> dict:
    cfg = load_defaults()["train"]
    cfg["densify"].update(changes.pop("densify", {}))
    cfg.update(changes)
    return cfg


@pytest.mark.parametrize("make", [random_neural, random_gaussians])
def test_the_loop_reads_the_device_only_at_flush_steps(tmp_path, training_reads, make):
    """log_every 5, refinement and checkpoints at multiples of 5 (so are the rules' refreshes,
    strategy.refresh_interval), 12 steps: the host reads tensors at steps 5, 10 and 12 only, with
    every rule on (σ ≥ 0 on every primitive, frequency cap, footprint floor, ray jitter, random
    backgrounds, the 3DGS opacity reset), the renderer (the fused CPU kernels) included."""
    cameras, images = views()
    cfg = small_config(iterations=12, batch_views=2, log_every=5, checkpoint_every=5, eval_every=0,
                       nonnegative_density=180.0, min_footprint=0.5, ray_jitter=0.5, random_background=True,
                       densify={"start": 5, "stop": 10, "every": 5})
    cfg["densify"]["gaussian"]["opacity_reset_every"] = 5
    log = []
    with training_reads as reads:
        train(make(20, seed=2), cameras, images, cfg, background=BG, extent=1.0, seed=0,
              alphas=torch.ones(3, 16, 16), on_step=lambda step, info: log.append((step, info)),
              checkpoint=lambda state: save_checkpoint(tmp_path / "checkpoint.safetensors", state))
    assert [step for step, _ in log] == list(range(1, 13))
    assert all(type(info["loss"]) is float and type(info["psnr"]) is float for _, info in log)
    read_steps = {step for step, _, _ in reads.seen}
    assert read_steps - {0} == {5, 10, 12}, reads.seen
    # one read of all the pending sums per flush
    flushes = [step for step, op, where in reads.seen if where == "radfield.core.trainer.loop.flush"]
    assert flushes == [5, 10, 12] and all(op == "tolist" for _, op, where in reads.seen if where.endswith(".flush"))


@pytest.mark.parametrize("batch", [1, 3])
def test_the_records_equal_reading_every_step(batch):
    """on_step gets the same records, bit for bit, whatever log_every is (the float64 device sums
    add in the order the Python floats did); only the moment they arrive differs."""
    cameras, images = views()
    cfg = small_config(iterations=9, batch_views=batch, eval_every=4, checkpoint_every=100,
                       densify={"start": 3, "stop": 6, "every": 3})
    held_out = lambda prims: loop.mean_psnr(prims, cameras[:1], images[:1], background=BG)
    logs = {}
    for every in (1, 4, None):
        logs[every] = []
        train(random_neural(20, seed=2), cameras, images, {**cfg, "log_every": every}, background=BG, extent=1.0,
              seed=0, held_out=held_out, on_step=lambda step, info, log=logs[every]: log.append((step, info)))
    assert logs[4] == logs[1] == logs[None]
    assert [step for step, info in logs[1] if "test_psnr" in info] == [4, 8, 9]


def test_reads_every_fifty_steps_by_default_on_a_gpu_only():
    assert loop.log_interval({"log_every": None}, torch.device("cpu")) == 1
    assert loop.log_interval({}, torch.device("cpu")) == 1   # a caller's own config without the key
    assert loop.log_interval({"log_every": None}, torch.device("cuda")) == loop.LOG_EVERY_GPU == 50
    assert loop.log_interval({"log_every": 7}, torch.device("cuda")) == 7
    with pytest.raises(ValueError, match="log_every"):
        loop.log_interval({"log_every": 0}, torch.device("cpu"))


def test_a_log_every_below_one_is_a_config_error():
    with pytest.raises(RadfieldError, match=r"^--set train.log_every=0: config key train.log_every must be at least 1.*got 0$"):
        load_config(None, ["train.log_every=0"])


# --- the train stage: log.jsonl and resume ----------------------------------------------------

def stage_context(tmp_path, name: str, log_every) -> Context:
    """A train-stage Context over a tiny scene.json (the data stage's contract) and init model."""
    data = tmp_path / "data"
    if not data.exists():
        data.mkdir()
        cameras, images = views(4)
        entries = []
        for camera, image in zip(cameras, images):
            write_image(data / f"{camera.name}.png", image.numpy())
            entries.append({"name": camera.name, "image": str(data / f"{camera.name}.png"), "fx": camera.fx,
                            "fy": camera.fy, "cx": camera.cx, "cy": camera.cy, "width": 16, "height": 16,
                            "c2w": camera.c2w.tolist(), "file_width": 16, "file_height": 16, "distortion": None})
        scene = {"version": 1, "format": "nerf_synthetic", "root": str(data), "posed": True, "downscale": 1,
                 "background": list(BG), "normalization": {"center": [0.0, 0.0, 0.0], "scale": 1 / 3.2},
                 "extent": 3.5, "splits": {"train": entries, "test": entries[:1]}}
        (data / "scene.json").write_text(json.dumps(scene))
        save_model(data / "init.safetensors", random_neural(20, extent=0.6, scale=0.2, seed=5))
    cfg = section(load_defaults(), train_stage.STAGE.config_keys)
    cfg["train"].update(iterations=10, checkpoint_every=5, eval_every=4, log_every=log_every)
    cfg["train"]["densify"].update(start=4, stop=8, every=4)
    root = tmp_path / name
    for sub in ("tmp", "work"):
        (root / sub).mkdir(parents=True)
    return Context(name="train", run_dir=tmp_path, stage_dir=root / "out", tmp=root / "tmp", work=root / "work",
                   config=cfg, inputs={"scene.json": data / "scene.json", "init.safetensors": data / "init.safetensors",
                                       "cage.npz": None},
                   outputs={out: root / "tmp" / out for out in train_stage.STAGE.outputs},
                   log=lambda line: None, quiet=True, device="cpu")


def without_seconds(path) -> list[str]:
    return [json.dumps({k: v for k, v in json.loads(line).items() if k != "seconds"}, sort_keys=True)
            for line in path.read_text().splitlines()]


def test_the_log_and_the_model_are_the_same_whatever_log_every(tmp_path, monkeypatch):
    """log.jsonl byte for byte (but seconds) and the model's bytes, for log_every 1 and 3; a run
    with log_every 3 killed at step 7 keeps its records to its last read, and resumes from its
    checkpoint (step 5, read first) to the same log and model."""
    every_step = stage_context(tmp_path, "every-step", 1)
    train_stage.run(every_step)
    every_third = stage_context(tmp_path, "every-third", 3)
    train_stage.run(every_third)
    log, model = (lambda ctx: ctx.outputs[train_stage.LOG]), (lambda ctx: ctx.outputs[train_stage.MODEL_FILE])
    assert without_seconds(log(every_third)) == without_seconds(log(every_step))
    assert len(without_seconds(log(every_step))) == 10
    assert model(every_third).read_bytes() == model(every_step).read_bytes()

    killed = stage_context(tmp_path, "killed", 3)
    write = train_stage.TrainLog.write

    def kill_at_7(self, record):
        if record["step"] == 7:
            raise KeyboardInterrupt
        write(self, record)

    monkeypatch.setattr(train_stage.TrainLog, "write", kill_at_7)
    with pytest.raises(KeyboardInterrupt):
        train_stage.run(killed)
    monkeypatch.undo()
    # reads at 3, 4 (refinement, held-out), 5 (checkpoint), 6: the kill came at the read of step 8
    assert [r["step"] for r in read_log(killed.work / train_stage.LOG)] == [1, 2, 3, 4, 5, 6]
    lines = []
    train_stage.run(dataclasses.replace(killed, log=lines.append))
    assert lines == ["resuming from the checkpoint at step 5"]
    assert without_seconds(log(killed)) == without_seconds(log(every_step))
    assert model(killed).read_bytes() == model(every_step).read_bytes()


def test_log_every_leaves_the_continue_key_alone(tmp_path):
    """A display setting: a finished run continues (and a killed one resumes) across a change of it."""
    keys = [train_stage._continue_key(stage_context(tmp_path, f"run{every}", every)) for every in (1, 50, None)]
    assert keys[0] == keys[1] == keys[2]
