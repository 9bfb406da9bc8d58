"""The official Splat the Net PLY (radfield/model_formats/stn_ply.py, issue 41): a tiny hand-made
file in the layout the official code writes (huynguyenbao/splat-the-net, GaussianModelMLP_HB.save_ply)
is detected and read as neural primitives with the expected tensors, renders in radfield as the
official rasterizer's equations say (huynguyenbao/diff-gaussian-mlp-max-rasterization,
forward_mlp.cu renderMLPCUDA and mlp_kernels.cu forward_mlp_siren, written out below in float64 per
pixel), to float32 precision; a damaged file is refused in one line; a 3DGS PLY stays a 3DGS PLY."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from radfield import model_formats
from radfield.core.geometry.cameras import Camera, look_at
from radfield.core.kinds import random_gaussians
from radfield.core.render.rasterize import render
from shared_helpers import one_line_error
from radfield.model_formats.ply_3dgs import gaussian_ply_bytes

N = 8          # the official kernel's hidden units
EPS = 1e-7     # utils.h
OMEGA = 30.0   # GaussianModelMLP_HB.omega
SH_C0, SH_C1 = 0.28209479177387814, 0.4886025119029199
BACKGROUND = (0.2, 0.4, 0.6)


def official_params(seed: int = 3) -> dict[str, np.ndarray]:
    """Three primitives as the official model holds them (its tensors' shapes): _xyz (P, 3),
    _features_dc (P, 1, 3), _features_rest (P, 3, 3) (SH degree 1), _opacity, _opacity_volr (P, 1),
    _scaling log (P, 3), _rotation (P, 4) w x y z unnormalised, _frequencies (P, N, 3), _phases,
    _amplitudes (P, N), _offsets (P, 1). Primitive 0 is dense (α reaches the 0.99 clamp), 1 has
    chords of negative integral (skipped), 2 is moderate; they overlap on screen."""
    rng = np.random.default_rng(seed)
    return {
        "xyz": np.array([[0.0, 0.0, 0.0], [0.25, 0.1, 0.3], [-0.2, -0.15, -0.35]]),
        "f_dc": rng.uniform(-1, 1, (3, 1, 3)),
        "f_rest": rng.uniform(-0.3, 0.3, (3, 3, 3)),
        "opacity": rng.uniform(-2, 2, (3, 1)),
        "opacity_volr": rng.uniform(-2, 2, (3, 1)),
        "scaling": np.log(np.array([[0.35, 0.2, 0.25], [0.3, 0.35, 0.15], [0.2, 0.3, 0.4]])),
        "rotation": np.array([[1.0, 0.2, -0.1, 0.3], [0.6, -0.3, 0.5, 0.1], [0.9, 0.1, 0.4, -0.6]]) * 1.7,
        "frequencies": rng.uniform(-1 / 3, 1 / 3, (3, N, 3)),
        "phases": rng.uniform(-1 / 3, 1 / 3, (3, N)),
        "amplitudes": rng.uniform(-1, 1, (3, N)) * np.array([[4.0], [0.6], [1.0]]),
        "offsets": np.array([[12.0], [0.1], [1.5]]),
    }


def official_ply(path, p: dict[str, np.ndarray], drop: str | None = None, patch=None) -> None:
    """`p` written as GaussianModelMLP_HB.save_ply writes its model: its attribute list and order,
    features and frequencies transposed (1, 2) and flattened, every property float32, plyfile's
    default (binary, native byte order). `drop`: a property left out; `patch(table)` edits the rows."""
    count = len(p["xyz"])
    flat = lambda a: a.transpose(0, 2, 1).reshape(count, a.shape[1] * a.shape[2])   # .transpose(1, 2).flatten(1)
    columns = [p["xyz"], np.zeros((count, 3)), flat(p["f_dc"]), flat(p["f_rest"]),
               p["opacity"], p["opacity_volr"], p["scaling"], p["rotation"],
               flat(p["frequencies"]), p["phases"], p["amplitudes"], p["offsets"]]
    names = ["x", "y", "z", "nx", "ny", "nz", *(f"f_dc_{i}" for i in range(3)),
             *(f"f_rest_{i}" for i in range(p["f_rest"].shape[1] * 3)), "opacity", "opacity_volr",
             *(f"scale_{i}" for i in range(3)), *(f"rot_{i}" for i in range(4)),
             *(f"frequencies_{i}" for i in range(p["frequencies"].shape[1] * 3)),
             *(f"phases_{i}" for i in range(p["phases"].shape[1])),
             *(f"amplitudes_{i}" for i in range(p["amplitudes"].shape[1])), "offsets"]
    values = np.concatenate(columns, 1)
    keep = [i for i, name in enumerate(names) if name != drop]
    table = np.empty(count, dtype=[(names[i], "f4") for i in keep])
    table[:] = list(map(tuple, values[:, keep]))
    if patch is not None:
        patch(table)
    PlyData([PlyElement.describe(table, "vertex")]).write(str(path))


def quat_matrix(q: np.ndarray) -> np.ndarray:
    """build_rotation of the official code (utils/general_utils.py): normalised w x y z -> R."""
    r, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - r * z), 2 * (x * z + r * y)],
                     [2 * (x * y + r * z), 1 - 2 * (x * x + z * z), 2 * (y * z - r * x)],
                     [2 * (x * z - r * y), 2 * (y * z + r * x), 1 - 2 * (x * x + y * y)]])


def official_render(p: dict[str, np.ndarray], w2c: np.ndarray, fx: float, fy: float, width: int, height: int,
                    eps: float = EPS):
    """The official forward pass, float64, per pixel: gaussian_mlp_max_renderer.render (ω·frequencies,
    ω·phases, exp scales, normalised rotations) then renderMLPCUDA / forward_mlp_siren. Returns the
    image (H, W, 3), the transmittance (H, W) and the per-pair (raw integral where hit, α used).
    `eps`: the kernel's EPS (in max(EPS, A) and in each unit's 1/(w̃ + EPS)); 0: the exact integral."""
    rot_v, t_v = w2c[:3, :3], w2c[:3, 3]
    campos = -rot_v.T @ t_v
    j, i = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.stack([(j - width / 2 + 0.5) / fx, (i - height / 2 + 0.5) / fy, np.ones_like(j)], -1)
    pix /= np.linalg.norm(pix, axis=-1, keepdims=True)             # pixDir, camera frame
    scales = np.exp(p["scaling"])
    mean_view = p["xyz"] @ rot_v.T + t_v
    order = [k for k in np.argsort(mean_view[:, 2], kind="stable") if mean_view[k, 2] > 0.2]   # in_frustum, depth sort
    T = np.ones((height, width))
    color = np.zeros((height, width, 3))
    done = np.zeros((height, width), bool)
    seen = []
    for k in order:
        # computeColorFromSH, degree 1: dir = μ − campos
        d = p["xyz"][k] - campos
        x, y, z = d / np.linalg.norm(d)
        sh = np.concatenate([p["f_dc"][k], p["f_rest"][k]], 0)      # (4, 3)
        rgb = np.maximum(SH_C0 * sh[0] - SH_C1 * y * sh[1] + SH_C1 * z * sh[2] - SH_C1 * x * sh[3] + 0.5, 0.0)
        # computeInvMatModelView: S⁻¹ R_modelᵀ R_viewᵀ
        m = np.diag(1 / scales[k]) @ quat_matrix(p["rotation"][k]).T @ rot_v.T
        dir_m = pix @ m.T
        xyz_m = m @ mean_view[k]
        a = np.maximum(eps, (dir_m * dir_m).sum(-1))
        b = dir_m @ xyz_m
        c = xyz_m @ xyz_m - 1.0
        disc = b * b - a * c
        hit = disc > 0
        root = np.sqrt(np.where(hit, disc, 0.0))
        t0, t1 = (b - root) / a, (b + root) / a
        inv_max_radius = 1 / scales[k].max()
        d_tilde = pix @ rot_v * inv_max_radius                     # inv_rot_view · pixDir / max s
        o_tilde = rot_v.T @ mean_view[k] * (-inv_max_radius)
        w1 = OMEGA * p["frequencies"][k]                           # weight1 = ω frequencies (N, 3)
        b1 = OMEGA * p["phases"][k]
        w1_t = d_tilde @ w1.T                                      # (H, W, N)
        b1_t = w1 @ o_tilde + b1
        raw = p["offsets"][k, 0] * (t1 - t0)
        raw = raw + (p["amplitudes"][k] / (w1_t + eps)
                     * (np.sin(b1_t + w1_t * t1[..., None]) - np.sin(b1_t + w1_t * t0[..., None]))).sum(-1)
        ok = hit & (raw > 0)
        integral = raw * np.linalg.norm(d_tilde, axis=-1)
        alpha = np.minimum(0.99, 1 - np.exp(-integral))
        ok &= alpha >= 1 / 255
        test_t = T * (1 - alpha)
        stop = ok & ~done & (test_t < 1e-4)
        done |= stop
        use = ok & ~done
        color += np.where(use[..., None], rgb * alpha[..., None] * T[..., None], 0.0)
        T = np.where(use, test_t, T)
        seen.append((np.where(hit, raw, np.nan), np.where(use, alpha, 0.0)))
    return color + T[..., None] * np.array(BACKGROUND), T, seen


def camera(width: int = 40, height: int = 32) -> Camera:
    fx = fy = 110.0
    c2w = look_at(torch.tensor([1.3, -2.4, 1.1]), torch.tensor([0.0, 0.0, 0.0]))
    return Camera(fx=fx, fy=fy, cx=width / 2, cy=height / 2, width=width, height=height, c2w=c2w)


@pytest.fixture
def stn_file(tmp_path):
    p = official_params()
    path = tmp_path / "point_cloud.ply"
    official_ply(path, p)
    return path, p


def test_the_official_layout_is_detected_and_read_as_the_neural_kind(stn_file, tmp_path):
    path, p = stn_file
    assert model_formats.detect(path).name == "stn-ply"
    prims = model_formats.read(path)
    assert prims.kind == "neural" and prims.omega0 == OMEGA and prims.window is False and prims.hidden == N
    f32 = lambda a: torch.from_numpy(np.asarray(a, np.float32))
    assert torch.equal(prims.means, f32(p["xyz"]))
    assert torch.equal(prims.log_scales, f32(p["scaling"]))
    assert torch.equal(prims.quats, f32(p["rotation"]))
    assert torch.equal(prims.sh, f32(np.concatenate([p["f_dc"], p["f_rest"]], 1)))
    assert torch.equal(prims.w1, f32(p["frequencies"]))        # (P, N, 3): the file's axis-major order undone
    assert torch.equal(prims.b1, f32(p["phases"]))
    assert torch.equal(prims.w2, f32(p["amplitudes"]))
    assert torch.equal(prims.b2, f32(p["offsets"][:, 0]))
    # ... and a 3DGS PLY is still a 3DGS PLY, whose reader refuses the official file
    gs = tmp_path / "gaussians.ply"
    gs.write_bytes(gaussian_ply_bytes(random_gaussians(5, sh_degree=1, seed=1)))
    assert model_formats.detect(gs).name == "ply-3dgs"
    assert model_formats.read(gs).kind == "gaussian"
    assert "stn-ply" in one_line_error(lambda: model_formats.read(path, format="ply-3dgs"))
    assert "Splat the Net" in one_line_error(lambda: model_formats.read(gs, format="stn-ply"))


@pytest.mark.parametrize("kernels", ["default", "torch"])
def test_radfield_draws_what_the_official_rasterizer_computes(stn_file, kernels, monkeypatch):
    """float32 (the file's numbers): within float32 rounding of the official equations, at phases
    ω0 (W1·u + b1) of up to ~150 rad (the camera ~8 radii away, as in any scene), whose float32
    rounding (~1e-5 rad) both renderers share. float64: equal to the exact equations (the official
    kernel with EPS = 0) to 1e-10; the kernel's EPS itself moves the image by < 1e-6."""
    if kernels == "torch":
        monkeypatch.setenv("RADFIELD_KERNELS", "torch")
    else:
        monkeypatch.delenv("RADFIELD_KERNELS", raising=False)
    path, p = stn_file
    cam = camera()
    prims = model_formats.read(path)
    with torch.no_grad():
        out32 = render(prims, cam, background=BACKGROUND)
        out64 = render(prims.to(dtype=torch.float64), cam, background=BACKGROUND)
    # the official equations on the float32 numbers of the file, in float64
    p32 = {k: np.asarray(v, np.float32).astype(np.float64) for k, v in p.items()}
    args = (p32, cam.w2c.numpy(), cam.fx, cam.fy, cam.width, cam.height)
    expected, transmittance, seen = official_render(*args)
    exact, exact_t, _ = official_render(*args, eps=0.0)
    # the scene exercises what it should: the 0.99 clamp, chords of negative integral (skipped),
    # overlaps, and no early termination (T stays above 1e-4)
    assert max(float(a.max()) for _, a in seen) == pytest.approx(0.99)
    assert sum(int((raw <= 0).sum()) for raw, _ in seen) > 20
    assert int((sum((a > 0).astype(int) for _, a in seen) >= 2).sum()) > 50
    assert transmittance.min() > 2e-4 and (transmittance < 1).mean() > 0.3

    def worst(out, color, t):
        return (np.abs(out.color.double().numpy() - color).max(), np.abs((1 - out.alpha.double().numpy()) - t).max())

    assert max(worst(out64, exact, exact_t)) < 1e-10
    assert max(worst(out64, expected, transmittance)) < 1e-6
    dc, dt = worst(out32, expected, transmittance)
    assert dc < 2e-5 and dt < 1e-4, (dc, dt)


def test_damaged_or_out_of_range_files_are_refused_in_one_line(tmp_path):
    p = official_params()
    cases = {
        "missing": dict(drop="offsets"),
        "missing_phase": dict(drop="phases_7"),
        "nan": dict(patch=lambda t: t.__setitem__("amplitudes_3", np.array([0, np.nan, 0], np.float32))),
        "range": dict(patch=lambda t: t.__setitem__("scale_1", np.array([0, 0, 40], np.float32))),
        "frequency": dict(patch=lambda t: t.__setitem__("frequencies_5", np.array([0, 1e6, 0], np.float32))),
    }
    expected = {"missing": "offsets", "missing_phase": "phases_", "nan": "amplitudes_3", "range": "scale_",
                "frequency": "frequencies_"}
    for name, how in cases.items():
        path = tmp_path / f"{name}.ply"
        official_ply(path, p, **how)
        assert model_formats.detect(path).name == "stn-ply"
        assert expected[name] in one_line_error(lambda: model_formats.read(path)), name
    # a wrong count: 7 hidden units' phases and amplitudes beside 8 units' frequencies
    q = dict(p, phases=p["phases"][:, :7], amplitudes=p["amplitudes"][:, :7])
    official_ply(tmp_path / "count.ply", q)
    assert "frequencies_" in one_line_error(lambda: model_formats.read(tmp_path / "count.ply"))
    # truncated: the header promises more rows than the file holds
    official_ply(tmp_path / "whole.ply", p)
    whole = (tmp_path / "whole.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(whole[: len(whole) - 40])
    assert "Splat the Net" in one_line_error(lambda: model_formats.read(tmp_path / "cut.ply"))


def test_a_file_without_primitives_is_refused(tmp_path):
    p = {k: v[:0] for k, v in official_params().items()}
    official_ply(tmp_path / "empty.ply", p)
    assert "no primitives" in one_line_error(lambda: model_formats.read(tmp_path / "empty.ply"))

