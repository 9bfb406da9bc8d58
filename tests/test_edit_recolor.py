"""Recolouring and appearance transfer (radfield.edit.recolor)."""

import numpy as np
import pytest
import torch

from radfield.errors import RadfieldError
from radfield.core.kinds import random_neural
from radfield.core.splat.sh import C0, eval_sh
from radfield.edit.field import Field
from radfield.edit.recolor import hue_matrix, peak_density
from radfield.edit.spec import EditContext, apply_operations, parse_spec


def run(fld, op, **ctx):
    return apply_operations(fld, parse_spec({"operations": [op]}), EditContext(**ctx))


def colour(sh, d):
    return eval_sh(sh, d.expand(len(sh), 3), 1) + 0.5      # before the clamp at 0


def test_recolor_changes_selected_and_leaves_the_rest_bit_identical():
    prims = random_neural(40, sh_degree=1, extent=1.0, seed=1).to(dtype=torch.float64)
    box = {"box": {"min": [-1, -1, -1], "max": [0, 1, 1]}}
    sel = prims.means[:, 0] <= 0
    d = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64), dim=-1)
    for rule, expect in (({"multiply": [0.5, 1.0, 2.0]}, lambda c: c * torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)),
                         ({"hue": 120}, lambda c: c @ torch.as_tensor(hue_matrix(120)).T)):
        out = run(Field(prims), {"recolor": {"select": box, **rule}})
        assert out.notes[-1]["selected"] == int(sel.sum())
        for name, tensor in prims.tensors().items():
            if name != "sh":
                assert torch.equal(getattr(out.prims, name), tensor)
        assert torch.equal(out.prims.sh[~sel], prims.sh[~sel])
        # exact for every view direction: c'(d) = m ⊙ c(d), resp. H c(d)
        assert torch.allclose(colour(out.prims.sh[sel], d), expect(colour(prims.sh[sel], d)), atol=1e-12)
    assert np.allclose(hue_matrix(120) @ [1, 0, 0], [0, 1, 0]) and np.allclose(hue_matrix(77) @ [1, 1, 1], [1, 1, 1])
    out = run(Field(prims), {"recolor": {"select": "all", "set": [0.2, 0.4, 0.6]}})
    assert torch.allclose(out.prims.sh[:, 0] * C0 + 0.5, torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64).expand(40, 3))


def test_density_above_selects_dense_primitives():
    prims = random_neural(10, seed=2, b2=0.2, w2_amplitude=0.05)
    prims.b2[:3] = 5.0
    peak = peak_density(prims)
    assert (peak[:3] > 4).all() and (peak[3:] < 1).all()
    out = run(Field(prims), {"recolor": {"select": {"density_above": 2.0}, "multiply": [0, 0, 0]}})
    assert out.notes[-1]["selected"] == 3
    assert torch.equal(out.prims.sh[3:], prims.sh[3:])


def test_transfer_fits_the_colour_of_a_reference(tmp_path):
    prims = random_neural(12, sh_degree=0, extent=0.3, scale=0.15, b2=2.0, seed=3)
    reference = run(Field(prims), {"recolor": {"select": "all", "multiply": [1.6, 0.5, 0.5]}})
    (tmp_path / "ref.safetensors").write_bytes(b"")
    out = run(Field(prims), {"transfer": {"select": {"sphere": {"center": [0, 0, 0], "radius": 10}}, "from": "ref.safetensors",
                                          "steps": 40, "views": 4, "size": 24}},
              base_dir=tmp_path, load_operand=lambda path: reference)
    note = out.notes[-1]
    assert note["psnr_after"] > note["psnr_before"] + 5
    for name, tensor in prims.tensors().items():
        if name != "sh":
            assert torch.equal(getattr(out.prims, name), tensor)      # geometry frozen


@pytest.mark.parametrize("op, message", [
    ({"recolor": {"select": "all"}}, "operations[0].recolor: give exactly one of"),
    ({"recolor": {"select": "all", "multiply": [1, 2]}}, "operations[0].recolor.multiply:"),
    ({"recolor": {"multiply": [1, 1, 1]}}, "operations[0].recolor.select: required"),
    ({"recolor": {"select": {"cube": 1}, "hue": 3}}, "operations[0].recolor.select: unknown selection"),
    ({"recolor": {"select": {"density_above": "x"}, "hue": 3}}, "operations[0].recolor.select.density_above:"),
    ({"transfer": {"select": "all"}}, "operations[0].transfer.from: required"),
])
def test_bad_recolor_entries_are_one_line(tmp_path, op, message):
    prims = random_neural(4, seed=4)
    sh = prims.sh.clone()
    with pytest.raises(RadfieldError) as info:
        run(Field(prims), op, base_dir=tmp_path)
    assert str(info.value).startswith(message) and "\n" not in str(info.value)
    assert torch.equal(prims.sh, sh) and list(tmp_path.iterdir()) == []


def write_posed_images(root, prims, cams, background=(1.0, 1.0, 1.0)):
    """A NeRF-synthetic dataset (transforms_train.json, OpenGL poses) of renders of `prims`."""
    import json
    import math

    from radfield.core.geometry.cameras import opencv_to_opengl
    from radfield.core.render.rasterize import render
    from radfield.datasets.images import write_image

    (root / "train").mkdir(parents=True)
    frames = []
    for k, cam in enumerate(cams):
        with torch.no_grad():
            write_image(root / "train" / f"r_{k}.png", render(prims, cam, background=background).color.clamp(0, 1).numpy())
        frames.append({"file_path": f"./train/r_{k}", "transform_matrix": opencv_to_opengl(cam.c2w).tolist()})
    angle = 2 * math.atan(cams[0].width / (2 * cams[0].fx))
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return root


def test_transfer_from_posed_images(tmp_path):
    from radfield.core.geometry.cameras import Camera, look_at
    from radfield.core.splat.sh import C0

    # two blobs; the photos show the right one recoloured (the paper's snowman: one region takes
    # the appearance of the photos, geometry frozen)
    prims = random_neural(24, sh_degree=0, extent=0.25, scale=0.15, b2=3.0, seed=6)
    prims.means[12:, 0] += 0.5
    prims.means[:12, 0] -= 0.5
    right = {"box": {"min": [0.0, -2, -2], "max": [2, 2, 2]}}
    photo = run(Field(prims), {"recolor": {"select": right, "set": [0.9, 0.2, 0.1]}}).prims
    cams = []
    for k in range(8):
        a = 2 * np.pi * k / 8
        eye = (3 * np.cos(a), 3 * np.sin(a), 0.8)
        cams.append(Camera(fx=40.0, fy=40.0, cx=24.0, cy=24.0, width=48, height=48, c2w=look_at(eye, (0, 0, 0))))
    write_posed_images(tmp_path / "photos", photo, cams)
    out = run(Field(prims), {"transfer": {"select": right, "images": "photos", "steps": 60, "views": 6, "size": 24}},
              base_dir=tmp_path)
    note = out.notes[-1]
    assert note["source"] == "images" and note["views"] == 6 and note["selected"] == 12
    assert note["psnr_after"] > note["psnr_before"] + 3
    # the selected primitives' colours moved toward the photos' colour
    colour = lambda p: p.sh[12:, 0] * C0 + 0.5
    target = torch.tensor([0.9, 0.2, 0.1])
    assert (colour(out.prims) - target).norm(dim=-1).mean() < 0.5 * (colour(prims) - target).norm(dim=-1).mean()
    # unselected primitives and every geometry tensor bit-identical
    assert torch.equal(out.prims.sh[:12], prims.sh[:12])
    for name, tensor in prims.tensors().items():
        if name != "sh":
            assert torch.equal(getattr(out.prims, name), tensor)


def test_transfer_from_images_errors(tmp_path):
    prims = random_neural(4, seed=4)
    (tmp_path / "photos").mkdir()
    for op, message in (({"select": "all", "images": "missing"}, "operations[0].transfer.images:"),
                        ({"select": "all", "images": "photos"}, "operations[0].transfer.images:"),
                        ({"select": "all", "images": "photos", "from": "x"}, "operations[0].transfer.from: required"),
                        ({"select": "all", "from": "x", "split": "test"}, "operations[0].transfer: split and background")):
        with pytest.raises(RadfieldError) as info:
            run(Field(prims), {"transfer": op}, base_dir=tmp_path)
        assert str(info.value).startswith(message) and "\n" not in str(info.value), str(info.value)
