"""Front-to-back compositing (radfield.core.splat.composite.composite_pairs, paper eq. 4) against
a direct per-pixel loop: C = Σ c_i α_i Π_{j<i}(1 − α_j), stopping before the pair that would take
the transmittance below t_min."""

import math
import random

import pytest
import torch

from radfield.core.splat.composite import composite_pairs

T_MIN = 1e-4


def random_pairs(seed: int, n_pix: int = 40, opaque_pixels: int = 10):
    """Pairs (pixel, rank, α) (N,) in a shuffled order: each pixel gets a random subset of the
    primitive ranks 0..29 with α in (0, 0.99]; the first `opaque_pixels` pixels get large α, so
    that their transmittance falls below T_MIN and they terminate early."""
    rng = random.Random(seed)
    pairs = []
    for pix in range(n_pix):
        ranks = rng.sample(range(30), rng.randint(0, 30))
        for r in ranks:
            a = rng.uniform(0.3, 0.99) if pix < opaque_pixels else rng.uniform(1e-3, 0.2)
            pairs.append((pix, r, a))
    rng.shuffle(pairs)
    pix, rank, alpha = zip(*pairs)
    return torch.tensor(pix), torch.tensor(rank), torch.tensor(alpha, dtype=torch.float64)


def loop_reference(pix, rank, alpha, n_pix, t_min, start=None):
    """Eq. 4 by hand, pixel by pixel in depth order: (weight per input pair, included per input
    pair, transmittance per pixel, whether each pixel terminated). start: transmittance per pixel
    from earlier pairs (1)."""
    weight = [0.0] * len(pix)
    included = [False] * len(pix)
    trans = [1.0 if start is None else start[p] for p in range(n_pix)]
    stopped = [False] * n_pix
    by_pixel = {}
    for i, (p, r) in enumerate(zip(pix.tolist(), rank.tolist())):
        by_pixel.setdefault(p, []).append((r, i))
    for p, items in by_pixel.items():
        for _, i in sorted(items):
            a = float(alpha[i])
            if trans[p] * (1.0 - a) < t_min:
                stopped[p] = True
                break
            weight[i] = trans[p] * a
            included[i] = True
            trans[p] *= 1.0 - a
    return torch.tensor(weight, dtype=torch.float64), torch.tensor(included), torch.tensor(trans, dtype=torch.float64), stopped


def in_input_order(out, values):
    """Per-pair values of a Composited (in composite order) put back in the order of its input."""
    back = torch.empty_like(values)
    back[out.order] = values
    return back


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pairs_match_a_per_pixel_loop_with_early_termination(seed):
    n_pix = 40
    pix, rank, alpha = random_pairs(seed, n_pix)
    out = composite_pairs(pix, rank, alpha, torch.zeros(n_pix, dtype=torch.float64), T_MIN)
    weight, included, trans, stopped = loop_reference(pix, rank, alpha, n_pix, T_MIN)
    assert sum(stopped) >= 5                       # the opaque pixels did terminate
    assert torch.equal(out.pixel, pix[out.order])
    assert torch.equal(in_input_order(out, out.included), included)
    torch.testing.assert_close(in_input_order(out, out.weight), weight, atol=1e-14, rtol=1e-12)
    torch.testing.assert_close(torch.exp(out.log_t), trans, atol=1e-14, rtol=1e-12)
    assert out.log_t.dtype == torch.float64
    # a pixel's pairs come out front to back
    key = out.pixel * 30 + rank[out.order]
    assert bool((key[1:] > key[:-1]).all())


def test_colour_accumulated_from_the_weights_is_eq4():
    n_pix = 25
    pix, rank, alpha = random_pairs(7, n_pix)
    colours = torch.rand(30, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out = composite_pairs(pix, rank, alpha, torch.zeros(n_pix, dtype=torch.float64), T_MIN)
    image = torch.zeros(n_pix, 3, dtype=torch.float64).index_add(0, out.pixel, out.weight[:, None] * colours[rank[out.order]])
    expected = torch.zeros(n_pix, 3, dtype=torch.float64)
    for p in range(n_pix):
        t = 1.0
        for r, a in sorted((int(r), float(a)) for q, r, a in zip(pix, rank, alpha) if int(q) == p):
            if t * (1 - a) < T_MIN:
                break
            expected[p] += t * a * colours[r]
            t *= 1 - a
    torch.testing.assert_close(image, expected, atol=1e-14, rtol=1e-12)


@pytest.mark.parametrize("seed", [3, 4])
def test_depth_chunks_carry_log_transmittance_over(seed):
    """Pairs composited in three depth batches (ranks 0-9, 10-19, 20-29), each batch starting from
    the log-transmittance the earlier ones left and without the pixels that terminated (as the
    renderer's chunks do), give the single call's result."""
    n_pix = 40
    pix, rank, alpha = random_pairs(seed, n_pix)
    whole = composite_pairs(pix, rank, alpha, torch.zeros(n_pix, dtype=torch.float64), T_MIN)
    weight, included, trans, stopped = loop_reference(pix, rank, alpha, n_pix, T_MIN)

    log_t = torch.zeros(n_pix, dtype=torch.float64)
    done = torch.zeros(n_pix, dtype=torch.bool)
    chunk_weight = torch.zeros(len(pix), dtype=torch.float64)
    chunk_included = torch.zeros(len(pix), dtype=torch.bool)
    terminated_in = {}
    for lo in (0, 10, 20):
        sel = torch.nonzero((rank >= lo) & (rank < lo + 10) & ~done[pix]).squeeze(1)
        out = composite_pairs(pix[sel], rank[sel], alpha[sel], log_t, T_MIN)
        log_t = out.log_t
        chunk_weight[sel[out.order]] = out.weight
        chunk_included[sel[out.order]] = out.included
        for p in out.pixel[~out.included].tolist():
            terminated_in.setdefault(p, lo)
        done[out.pixel[~out.included]] = True
    assert len(set(terminated_in.values())) > 1    # pixels terminated in different batches
    assert torch.equal(chunk_included, included)
    assert done.tolist() == stopped
    torch.testing.assert_close(chunk_weight, weight, atol=1e-14, rtol=1e-12)
    torch.testing.assert_close(torch.exp(log_t), trans, atol=1e-14, rtol=1e-12)
    torch.testing.assert_close(log_t, whole.log_t, atol=1e-12, rtol=0)


def test_a_batch_starts_from_the_given_transmittance():
    n_pix = 30
    pix, rank, alpha = random_pairs(5, n_pix, opaque_pixels=0)
    start = [math.exp(-random.Random(p).uniform(0, 9)) for p in range(n_pix)]
    out = composite_pairs(pix, rank, alpha, torch.log(torch.tensor(start, dtype=torch.float64)), T_MIN)
    weight, included, trans, stopped = loop_reference(pix, rank, alpha, n_pix, T_MIN, start)
    assert any(stopped) and not all(stopped)       # the darker starts terminate, the others do not
    assert torch.equal(in_input_order(out, out.included), included)
    torch.testing.assert_close(in_input_order(out, out.weight), weight, atol=1e-14, rtol=1e-12)
    torch.testing.assert_close(torch.exp(out.log_t), trans, atol=1e-14, rtol=1e-12)


def test_t_min_zero_composites_every_pair():
    n_pix = 40
    pix, rank, alpha = random_pairs(6, n_pix)
    out = composite_pairs(pix, rank, alpha, torch.zeros(n_pix, dtype=torch.float64), 0.0)
    assert bool(out.included.all())
    product = [1.0] * n_pix
    for p, a in zip(pix.tolist(), alpha.tolist()):
        product[p] *= 1.0 - a
    torch.testing.assert_close(torch.exp(out.log_t), torch.tensor(product, dtype=torch.float64), atol=1e-300, rtol=1e-12)


def test_float32_alpha_keeps_float64_transmittance_and_is_differentiable():
    n_pix = 12
    pix, rank, alpha = random_pairs(8, n_pix, opaque_pixels=4)
    out32 = composite_pairs(pix, rank, alpha.float(), torch.zeros(n_pix, dtype=torch.float64), T_MIN)
    assert out32.weight.dtype == torch.float32 and out32.log_t.dtype == torch.float64
    weight, included, _, _ = loop_reference(pix, rank, alpha.float().double(), n_pix, T_MIN)
    torch.testing.assert_close(in_input_order(out32, out32.weight).double(), weight, atol=1e-6, rtol=1e-5)

    # d(weights, log T)/dα by autograd against finite differences (termination is a fixed mask)
    def f(a):
        out = composite_pairs(pix, rank, a, torch.zeros(n_pix, dtype=torch.float64), T_MIN)
        return torch.cat([out.weight, out.log_t])
    assert torch.autograd.gradcheck(f, (alpha.clone().requires_grad_(True),), eps=1e-7, atol=1e-6)


def test_no_pairs():
    empty = torch.zeros(0, dtype=torch.int64)
    log_t = torch.full((4,), -0.5, dtype=torch.float64)
    out = composite_pairs(empty, empty, torch.zeros(0, dtype=torch.float64), log_t, T_MIN)
    assert out.weight.numel() == 0 and out.order.numel() == 0
    assert torch.equal(out.log_t, log_t)
