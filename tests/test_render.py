"""The fast renderer against slow references: quadrature, a per-pixel loop, finite differences."""

import math

import pytest
import torch

from radfield.core.geometry.cameras import Camera, look_at, opengl_to_opencv
from radfield.core.kinds.neural_density import neural_line_integral
from radfield.core.kinds import NeuralPrimitives, quat_to_rotmat, random_gaussians, random_neural, rotmat_to_quat
from radfield.core.render.rasterize import render
from radfield.core.kinds.neural_density import quadrature_optical_depth
from radfield.core.render.reference import reference_render
from radfield.core.splat.sh import eval_sh

torch.set_default_dtype(torch.float32)


def small_camera(eye=(0.3, -3.0, 0.5), width=16, height=14) -> Camera:
    # off-centre principal point and non-square pixels catch swapped axes and offsets
    return Camera(fx=20.0, fy=22.0, cx=8.3, cy=6.7, width=width, height=height, c2w=look_at(eye, (0, 0, 0)))


def one_primitive_rays(prims: NeuralPrimitives, i: int, g: torch.Generator):
    """Rays through primitive i in the hard cases: generic, nearly perpendicular to an MLP
    frequency W1_k (a_k ≈ 0), grazing the ellipsoid, starting inside it."""
    mu = prims.means[i].double()
    rot = quat_to_rotmat(prims.quats[i][None].double())[0]
    s = torch.exp(prims.log_scales[i].double())
    rays = []
    for kind in ("generic", "perpendicular", "grazing", "inside"):
        for _ in range(3):
            if kind == "perpendicular":
                k = int(torch.randint(prims.hidden, (1,), generator=g))
                w = prims.w1[i, k].double()
                d = torch.linalg.cross(w, torch.randn(3, generator=g, dtype=torch.float64))
                d = d / d.norm()
                d = d + 1e-7 * w / w.norm()  # a_k of order 1e-6: the unstable case of eq. 8
            else:
                d = torch.randn(3, generator=g, dtype=torch.float64)
            d = d / d.norm()
            if kind == "inside":
                p = mu + rot @ (s * 0.6 * torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=0))
                rays.append((p, d))
                continue
            # aim at a point of the ellipsoid's cross-section; grazing: just inside the silhouette
            e = torch.linalg.cross(d, torch.randn(3, generator=g, dtype=torch.float64))
            e = e / e.norm()
            # boundary of the ellipsoid along e (in the plane ⟂ d): bisect on the inside test
            lo, hi = 0.0, float(s.max()) * 2
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                # the ray through mu + mid e with direction d hits the ellipsoid iff the closest approach is inside
                o_ell = ((mu + mid * e - mu) @ rot) / s
                d_ell = (d @ rot) / s
                t = -(o_ell @ d_ell) / (d_ell @ d_ell)
                lo, hi = (mid, hi) if (o_ell + t * d_ell).norm() <= 1 else (lo, mid)
            offset = lo * (0.999 if kind == "grazing" else float(torch.rand(1, generator=g)) * 0.9)
            rays.append((mu + offset * e - 3 * float(s.max()) * d, d))
    return rays


@pytest.mark.parametrize("seed", [0, 1])
def test_closed_form_integral_matches_quadrature(seed):
    g = torch.Generator().manual_seed(seed)
    prims = random_neural(4, scale=0.3, w2_amplitude=1.0, b2=0.3, seed=seed).to(dtype=torch.float64)
    for i in range(len(prims)):
        one = prims.select([i])
        for origin, direction in one_primitive_rays(prims, i, g):
            fast = neural_line_integral(one, origin[None], direction[None])[0, 0].item()
            slow = quadrature_optical_depth(prims, i, origin, direction)
            assert fast == pytest.approx(slow, rel=1e-6, abs=1e-7), (origin, direction)


def test_integral_near_plane_and_miss():
    prims = random_neural(1, scale=0.5, seed=3).to(dtype=torch.float64)
    mu = prims.means[0]
    d = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    # ray starting behind the primitive's far side: nothing to integrate
    assert neural_line_integral(prims, (mu + 2 * d)[None], d[None]).item() == 0.0
    # clipping at l_min equals integrating from the clipped origin
    origin = mu - 2 * d
    clipped = neural_line_integral(prims, origin[None], d[None], l_min=2.1).item()
    assert clipped == pytest.approx(quadrature_optical_depth(prims, 0, origin, d, l_min=2.1), rel=1e-6, abs=1e-7)
    assert clipped != pytest.approx(neural_line_integral(prims, origin[None], d[None]).item(), rel=1e-3)


def test_integral_is_scale_invariant():
    """Optical depth is measured in units of the primitive's size: scaling the scene about the
    ray origin leaves it unchanged (what makes similarity edits exact)."""
    prims = random_neural(3, scale=0.3, seed=5).to(dtype=torch.float64)
    origin = torch.tensor([[0.1, -2.0, 0.2]], dtype=torch.float64)
    dirs = torch.nn.functional.normalize(prims.means - origin, dim=-1)
    base = neural_line_integral(prims, origin.expand(3, 3), dirs)
    k = 2.5
    scaled = NeuralPrimitives(means=origin + k * (prims.means - origin), log_scales=prims.log_scales + math.log(k),
                              quats=prims.quats, sh=prims.sh, w1=prims.w1, b1=prims.b1, w2=prims.w2, b2=prims.b2)
    torch.testing.assert_close(neural_line_integral(scaled, origin.expand(3, 3), dirs), base)


def scene(kind: str, dtype=torch.float64):
    if kind == "neural":
        prims = random_neural(10, sh_degree=2, scale=0.35, extent=0.6, b2=2.0, seed=1)
        # one big primitive around the camera (camera inside: integration starts at the near plane)
        # and one straddling the near plane
        eye = torch.tensor([0.3, -3.0, 0.5])
        prims.means[0] = eye + torch.tensor([0.05, 0.1, -0.05])
        prims.log_scales[0] = math.log(0.4)
        prims.b2[0] = 0.3
        prims.means[1] = eye + torch.tensor([0.0, 0.35, 0.0])
        prims.log_scales[1] = math.log(0.3)
    else:
        prims = random_gaussians(10, sh_degree=2, scale=0.15, extent=0.6, seed=1)
    return prims.to(dtype=dtype)


@pytest.mark.parametrize("kind", ["neural", "gaussian"])
def test_render_matches_per_pixel_reference(kind):
    prims, cam = scene(kind), small_camera()
    fast = render(prims, cam, background=(0.2, 0.3, 0.4), near=0.05)
    slow = reference_render(prims, cam, background=(0.2, 0.3, 0.4), near=0.05)
    assert fast.meta["contributing_pairs"] > 50
    assert (fast.color - slow).abs().max() < 1e-6


@pytest.mark.parametrize("kind", ["neural", "gaussian"])
def test_chunking_and_precision_do_not_change_the_image(kind):
    prims, cam = scene(kind), small_camera(width=24, height=20)
    whole = render(prims, cam)
    chunked = render(prims, cam, max_pairs=37)
    torch.testing.assert_close(chunked.color, whole.color, atol=1e-12, rtol=0)
    single = render(prims.to(dtype=torch.float32), cam)
    assert (single.color.double() - whole.color).abs().max() < 1e-4


def test_early_termination_stops_at_opaque_layers():
    # a wall of opaque primitives in front of a red one: the red one must not show and must be skipped
    n = 30
    # α stays below the 0.99 clamp, so no pixel sits exactly on the termination threshold
    wall = random_neural(n, scale=0.6, extent=0.3, b2=1.5, w2_amplitude=0.2, seed=2)
    wall.means[:, 1] = -1.0
    red = random_neural(1, scale=0.5, b2=40.0, w2_amplitude=0.0, seed=3)
    red.means[:] = torch.tensor([0.0, 1.0, 0.0])
    red.sh[:] = 0
    red.sh[0, 0, 0] = 2.0
    prims = NeuralPrimitives(**{k: torch.cat([getattr(wall, k), getattr(red, k)]) for k in wall.tensors()})
    prims = prims.to(dtype=torch.float64)
    cam = Camera(fx=30, fy=30, cx=8, cy=8, width=16, height=16, c2w=look_at((0, -4, 0), (0, 0, 0)))
    out = render(prims, cam, max_pairs=64)
    assert out.meta["terminated_pixels"] > 100
    assert out.meta["pairs"] < 0.6 * out.meta["candidate_pairs"]  # terminated pixels were skipped
    assert (out.color - reference_render(prims, cam)).abs().max() < 1e-9
    # the red primitive is hidden wherever the wall is opaque
    wall_only = render(prims.select(slice(0, n)), cam)
    opaque = wall_only.alpha > 0.999
    assert opaque.sum() > 100 and (out.color - wall_only.color)[opaque].abs().max() < 1e-3


@pytest.mark.parametrize("kind", ["neural", "gaussian"])
def test_sort_order_front_primitive_wins(kind):
    """Two overlapping primitives, red and blue: whichever is nearer the camera dominates the centre
    pixel, and swapping their depths swaps the result (a renderer that sorts by anything else fails)."""
    make = (lambda: random_neural(2, scale=0.4, b2=1.5, w2_amplitude=0.0, seed=0)) if kind == "neural" else (
        lambda: random_gaussians(2, scale=0.3, seed=0))
    cam = Camera(fx=40, fy=40, cx=8, cy=8, width=16, height=16, c2w=look_at((0, -4, 0), (0, 0, 0)))
    centre = []
    for red_y in (-0.5, 0.5):
        prims = make()
        prims.means[:] = torch.tensor([[0.0, red_y, 0.0], [0.0, -red_y, 0.0]])
        prims.quats[:] = torch.tensor([1.0, 0, 0, 0])
        prims.sh[:] = 0
        prims.sh[0, 0] = torch.tensor([2.0, -2.0, -2.0])  # red
        prims.sh[1, 0] = torch.tensor([-2.0, -2.0, 2.0])  # blue
        if kind == "gaussian":
            prims.opacities[:] = 3.0
        centre.append(render(prims, cam).color[8, 8])
    red_front, blue_front = centre
    assert red_front[0] > red_front[2] + 0.3
    assert blue_front[2] > blue_front[0] + 0.3


@pytest.mark.parametrize("kind", ["neural", "gaussian"])
def test_projection_lands_on_the_pinhole_pixel(kind):
    """A small primitive at a known point appears at K (R x + t), in an OpenGL-authored camera."""
    c2w_gl = torch.tensor([[1.0, 0, 0, 0.2], [0, 0, -1, -4.0], [0, 1, 0, 0.1], [0, 0, 0, 1]])  # looks along +y
    cam = Camera(fx=50, fy=60, cx=20, cy=14, width=40, height=30, c2w=opengl_to_opencv(c2w_gl))
    point = torch.tensor([0.5, 0.3, 0.4])
    w2c = cam.w2c.float()
    p = w2c[:3, :3] @ point + w2c[:3, 3]
    u, v = cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy
    assert p[2] > 0 and v < cam.cy and u > cam.cx  # +z world is up in the image, +x right
    # a round primitive a few pixels wide: its alpha-weighted centroid is the projected centre
    prims = (random_neural(1, b2=0.5, w2_amplitude=0.0) if kind == "neural" else random_gaussians(1))
    prims.means[0] = point
    prims.log_scales[:] = math.log(0.5 if kind == "neural" else 0.06)
    out = render(prims, cam, background=(0, 0, 0))
    weight = out.alpha
    ii, jj = torch.meshgrid(torch.arange(30) + 0.5, torch.arange(40) + 0.5, indexing="ij")
    assert float((weight * jj).sum() / weight.sum()) == pytest.approx(float(u), abs=0.1)
    assert float((weight * ii).sum() / weight.sum()) == pytest.approx(float(v), abs=0.1)
    assert float(out.depth[int(v), int(u)]) == pytest.approx(float(p[2]), rel=1e-5)


def _gradcheck(kind, name):
    prims, cam = scene(kind), small_camera(width=7, height=6)
    if kind == "neural":
        prims = prims.select(slice(2, 6))  # keep it small; primitives in front of the camera
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64)

    def f(x):
        p = prims.map(lambda t: t)
        if name == "background":
            return render(p, cam, background=x).color
        setattr(p, name, x)
        out = render(p, cam, background=bg)
        return torch.cat([out.color.flatten(), out.alpha.flatten(), out.depth.flatten() * 0.1])

    x = bg.clone() if name == "background" else getattr(prims, name).clone()
    assert torch.autograd.gradcheck(f, (x.requires_grad_(True),), eps=1e-6, atol=1e-5, rtol=1e-3)


@pytest.mark.parametrize("name", ["means", "log_scales", "quats", "w1", "b1", "w2", "b2", "sh", "background"])
def test_neural_gradients_match_finite_differences(name):
    _gradcheck("neural", name)


@pytest.mark.parametrize("name", ["means", "log_scales", "quats", "opacities", "sh"])
def test_gaussian_gradients_match_finite_differences(name):
    _gradcheck("gaussian", name)


def test_sh_basis_matches_scipy():
    """3DGS's real SH basis: sqrt(2) Im(Y_l^|m|) for m < 0, Y_l^0, sqrt(2) Re(Y_l^m) for m > 0,
    with scipy's (Condon-Shortley) complex harmonics; coefficients ordered m = -l..l per band."""
    special = pytest.importorskip("scipy.special")
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=torch.float64), dim=-1)
    theta, phi = torch.arccos(dirs[:, 2]).numpy(), torch.atan2(dirs[:, 1], dirs[:, 0]).numpy()
    k = 0
    for l in range(4):
        for m in range(-l, l + 1):
            y = special.sph_harm_y(l, abs(m), theta, phi)
            expected = {True: (2**0.5) * y.imag, False: (2**0.5) * y.real}[m < 0] if m != 0 else y.real
            coeffs = torch.zeros(50, 16, 3, dtype=torch.float64)
            coeffs[:, k, 0] = 1.0
            torch.testing.assert_close(eval_sh(coeffs, dirs, 3)[:, 0], torch.as_tensor(expected))
            k += 1


def test_quaternion_round_trip():
    q = torch.nn.functional.normalize(torch.randn(100, 4, dtype=torch.float64), dim=-1)
    r = quat_to_rotmat(q)
    torch.testing.assert_close(r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(100, 3, 3))
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(100, dtype=torch.float64))
    torch.testing.assert_close(quat_to_rotmat(rotmat_to_quat(r)), r)
