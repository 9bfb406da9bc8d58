"""Training over several ranks: rank 0 sends the trainer's inputs, every rank runs the trainer.

Rank 0 (the one that runs the pipeline) calls `train_on_ranks` with exactly the arguments of
radfield.core.trainer.loop.train; with several ranks it first broadcasts them (cameras, images, valid
masks, alpha channels, the initial primitives, the state to resume from, the train config) to the other ranks,
which wait in `follow` and then run the same trainer with them. So the other ranks need no
dataset, run directory or config file of their own (they may be on other machines), and they
never write a file: rank 0 alone logs, checkpoints and writes the outputs.
"""

from __future__ import annotations

from dataclasses import asdict, fields

import torch

from radfield.core.trainer import distributed
from radfield.core.geometry.cameras import Camera, Light
from radfield.core import kinds
from radfield.core.trainer.loop import TrainState, state_from_tensors, state_tensors, train


def train_on_ranks(prims, train_cameras, train_images, cfg, *, background, extent, seed, device="cpu",
                   near=0.01, start_state=None, masks=None, alphas=None, on_step=None, held_out=None,
                   checkpoint=None) -> TrainState:
    """loop.train on every rank of distributed.current() (just loop.train with one)."""
    world = distributed.current()
    kwargs = dict(background=[float(c) for c in background], extent=float(extent), seed=int(seed), near=float(near))
    if world.size > 1:
        dev = world.device(device)
        tensors = {"images": train_images, **{f"prims.{n}": t for n, t in prims.tensors().items()}}
        tensors.update({f"camera{k}.c2w": c.c2w for k, c in enumerate(train_cameras)})
        if masks is not None:
            tensors["masks"] = masks
        if alphas is not None:
            tensors["alphas"] = alphas
        if start_state is not None:
            tensors.update({f"start.{n}": t for n, t in state_tensors(start_state).items()})
        meta = {"cfg": cfg, "kwargs": kwargs, "device": dev.type, "kind": prims.kind,
                "attrs": kinds.of(prims).attrs(prims), "timeout": world.timeout, "check_every": world.check_every,
                "cameras": [camera_meta(c) for c in train_cameras],
                "start": None if start_state is None else
                {"step": start_state.step, "kind": start_state.kind, **start_state.attrs}}
        distributed.send("train", meta, tensors)
        distributed.start_training(world, dev)
        device = dev
    return train(prims, train_cameras, train_images, cfg, device=device, start_state=start_state, masks=masks,
                 alphas=alphas, on_step=on_step, held_out=held_out, checkpoint=checkpoint, world=world, **kwargs)


def camera_meta(camera: Camera) -> dict:
    """A camera's fields but c2w as JSON values: its conditions as they are, but a Light (the light
    condition's value) as ["Light", its fields]. Another condition's value must be a JSON value."""
    meta = {f.name: getattr(camera, f.name) for f in fields(camera) if f.name not in ("c2w", "conditions")}
    meta["conditions"] = {name: ["Light", asdict(value)] if isinstance(value, Light) else value
                          for name, value in camera.conditions.items()}
    return meta


def camera_from_meta(meta: dict, c2w: torch.Tensor) -> Camera:
    """The camera `camera_meta` described (JSON turns the light's tuples into lists)."""
    conditions = {name: _light(value[1]) if isinstance(value, list) and value[:1] == ["Light"] else value
                  for name, value in meta["conditions"].items()}
    return Camera(**{**meta, "conditions": conditions}, c2w=c2w)


def _light(sent: dict) -> Light:
    sent = {k: tuple(v) if isinstance(v, list) else v for k, v in sent.items()}
    light = Light(**sent)
    # Light normalises a direction again, which can move a unit vector by an ulp: every rank
    # must draw with rank 0's light bit for bit
    for name in ("position", "direction"):
        object.__setattr__(light, name, sent[name])
    return light


def follow() -> bool:
    """A rank other than 0: train whenever rank 0 says so, until it says it is done (True) or
    that it failed (False: it reports the error itself)."""
    world = distributed.current()
    while True:
        kind, meta, tensors = distributed.receive()
        if kind != "train":
            return kind == "done"
        world.timeout, world.check_every = meta["timeout"], meta["check_every"]
        device = world.device(meta["device"])
        cameras = [camera_from_meta(c, tensors[f"camera{k}.c2w"]) for k, c in enumerate(meta["cameras"])]
        prim_tensors = {n.removeprefix("prims."): t for n, t in tensors.items() if n.startswith("prims.")}
        prims = kinds.get(meta["kind"]).assemble(prim_tensors, meta["attrs"])
        start = meta["start"]
        start_state = None if start is None else state_from_tensors(
            start, {n.removeprefix("start."): t for n, t in tensors.items() if n.startswith("start.")})
        distributed.start_training(world, device)
        train(prims, cameras, tensors["images"], meta["cfg"], device=device, start_state=start_state,
              masks=tensors.get("masks"), alphas=tensors.get("alphas"), world=world, **meta["kwargs"])
        del tensors, prims, start_state
        if device.type == "cuda":
            torch.cuda.empty_cache()
