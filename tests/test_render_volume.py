"""Volume rendering maths: hand-computed rays, a float64 reference, and extreme inputs."""

import math

import pytest
import torch

from nerfmeta.render.volume import (
    alpha_from_tau,
    composite,
    expected_depth,
    packed_distortion,
    packed_weights,
    render_packed,
    render_weights,
    shifted_softplus,
    softplus_shift_for_alpha,
)


def test_three_sample_ray_by_hand():
    tau = torch.tensor([[0.5, 1.0, 2.0]], dtype=torch.float64)
    colors = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]], dtype=torch.float64)
    w, t_final = render_weights(tau)
    a = [1 - math.exp(-0.5), 1 - math.exp(-1.0), 1 - math.exp(-2.0)]
    expected = [a[0], math.exp(-0.5) * a[1], math.exp(-1.5) * a[2]]
    assert w[0].tolist() == pytest.approx(expected, rel=1e-12)
    assert t_final.item() == pytest.approx(math.exp(-3.5), rel=1e-12)
    rgb = composite(w, colors, t_final, torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64))
    assert rgb[0].tolist() == pytest.approx([e + math.exp(-3.5) for e in expected], rel=1e-12)


def test_five_sample_ray_with_empty_and_opaque_samples():
    # empty, empty, opaque (tau huge), then anything behind is invisible
    tau = torch.tensor([[0.0, 0.0, 1e16, 3.0, 0.2]])
    w, t_final = render_weights(tau)
    assert w[0].tolist() == [0.0, 0.0, 1.0, 0.0, 0.0]
    assert t_final.item() == 0.0
    depth = expected_depth(w, torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0]]), t_final, torch.tensor([6.0]))
    assert depth.item() == 3.0


def test_weights_sum_to_one_minus_final_transmittance():
    g = torch.Generator().manual_seed(0)
    tau = torch.rand(64, 40, generator=g) * 0.3
    w, t_final = render_weights(tau)
    torch.testing.assert_close(w.sum(-1) + t_final, torch.ones(64), atol=1e-6, rtol=0)


def _reference_float64(sigma, delta, colors, bg):
    """The textbook formula with products of (1 - alpha), in float64."""
    sigma, delta, colors, bg = (x.double() for x in (sigma, delta, colors, bg))
    alpha = 1 - torch.exp(-sigma * delta)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], -1), -1)
    w = trans * alpha
    t_final = torch.prod(1 - alpha, -1)
    return (w[..., None] * colors).sum(1) + t_final[:, None] * bg, w


def test_float32_matches_float64_reference_on_random_rays():
    g = torch.Generator().manual_seed(1)
    n, s = 256, 64
    sigma = torch.exp(torch.empty(n, s).uniform_(-7, 7, generator=g))  # 1e-3 .. 1e3
    delta = torch.exp(torch.empty(n, s).uniform_(-7, 0, generator=g))
    colors = torch.rand(n, s, 3, generator=g)
    bg = torch.tensor([1.0, 1.0, 1.0])
    w, t_final = render_weights(sigma * delta)
    rgb = composite(w, colors, t_final, bg)
    ref_rgb, ref_w = _reference_float64(sigma, delta, colors, bg)
    assert (rgb.double() - ref_rgb).abs().max().item() < 2e-6
    assert (w.double() - ref_w).abs().max().item() < 2e-6


EXTREME_SIGMA = [0.0, 1e-10, 1e-3, 1.0, 1e3, 1e6]
EXTREME_DELTA = [0.0, 1e-10, 1e-3, 1.0, 1e3, 1e10]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extreme_inputs_give_finite_outputs_and_gradients(dtype):
    # every pair of (sigma, delta) appears on one ray of 4 samples, mixed with ordinary samples
    pairs = [(s, d) for s in EXTREME_SIGMA for d in EXTREME_DELTA]
    sigma = torch.tensor([[0.5, s, 2.0, s] for s, _ in pairs], dtype=dtype, requires_grad=True)
    delta = torch.tensor([[0.1, d, 0.1, d] for _, d in pairs], dtype=dtype, requires_grad=True)
    colors = torch.rand(len(pairs), 4, 3, dtype=dtype, requires_grad=True)
    w, t_final = render_weights(sigma * delta)
    rgb = composite(w, colors, t_final, torch.ones(3, dtype=dtype))
    assert torch.isfinite(rgb).all() and torch.isfinite(w).all() and torch.isfinite(t_final).all()
    assert (w >= 0).all() and (w <= 1).all()
    assert (w.sum(-1) <= 1 + 1e-6).all()
    grads = torch.autograd.grad(rgb.sum() + w.sum(), (sigma, delta, colors))
    for g in grads:
        assert torch.isfinite(g).all()


def test_gradcheck_float64():
    g = torch.Generator().manual_seed(2)
    sigma = torch.rand(3, 5, generator=g, dtype=torch.float64).requires_grad_()
    delta = (torch.rand(3, 5, generator=g, dtype=torch.float64) + 0.1).requires_grad_()
    colors = torch.rand(3, 5, 3, generator=g, dtype=torch.float64).requires_grad_()

    def fn(s, d, c):
        w, t = render_weights(s * d)
        return composite(w, c, t, torch.ones(3, dtype=torch.float64))

    assert torch.autograd.gradcheck(fn, (sigma, delta, colors))


@pytest.mark.parametrize("alpha_init", [1e-6, 1e-4, 1e-2, 0.5])
@pytest.mark.parametrize("interval", [0.25, 1.0, 3.0])
def test_shift_gives_the_chosen_initial_alpha(alpha_init, interval):
    shift = softplus_shift_for_alpha(alpha_init, interval)
    raw = torch.zeros(1, dtype=torch.float64)
    alpha = alpha_from_tau(shifted_softplus(raw, shift) * interval)
    assert alpha.item() == pytest.approx(alpha_init, rel=1e-9)


def test_shift_rejects_out_of_range_alpha():
    for bad in (0.0, 1.0, -0.1, 2.0):
        with pytest.raises(ValueError, match="alpha_init"):
            softplus_shift_for_alpha(bad)


def test_alpha_from_tiny_tau_is_exact():
    tau = torch.tensor([1e-12, 1e-8], dtype=torch.float32)
    torch.testing.assert_close(alpha_from_tau(tau), tau, rtol=1e-6, atol=0)


# -- packed samples: the shared compositor ----------------------------------------------------


def test_packed_weights_equal_dense_render_weights_with_gradients():
    g = torch.Generator().manual_seed(2)
    counts = [3, 0, 5, 1]
    tau = (torch.rand(sum(counts), generator=g, dtype=torch.float64) * 2).requires_grad_()
    ray_idx = torch.repeat_interleave(torch.arange(4), torch.tensor(counts))
    w, t_final = packed_weights(tau, ray_idx, 4)
    dense = torch.zeros(4, max(counts), dtype=torch.float64)
    rank = torch.cat([torch.arange(c) for c in counts])
    dense = dense.index_put((ray_idx, rank), tau)
    w_d, t_d = render_weights(dense)
    torch.testing.assert_close(w, w_d[ray_idx, rank])
    torch.testing.assert_close(t_final, t_d)
    assert t_final[1] == 1.0
    torch.testing.assert_close(torch.zeros(4, dtype=torch.float64).index_add(0, ray_idx, w) + t_final,
                               torch.ones(4, dtype=torch.float64))
    torch.autograd.gradcheck(lambda v: packed_weights(v, ray_idx, 4), (tau,))


def test_render_packed_five_sample_ray_by_hand():
    """One 5-sample ray through the shared compositor: T, weights, colour, opacity and depth by hand."""
    tau = torch.tensor([0.0, 0.5, 1.0, 0.0, 2.0], dtype=torch.float64)
    t = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0], dtype=torch.float64)
    colours = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0], [0, 1.0, 1.0]], dtype=torch.float64)
    ray_idx = torch.zeros(5, dtype=torch.long)
    trans = [1.0, 1.0, math.exp(-0.5), math.exp(-1.5), math.exp(-1.5)]
    alpha = [0.0, 1 - math.exp(-0.5), 1 - math.exp(-1.0), 0.0, 1 - math.exp(-2.0)]
    w = torch.tensor([a * b for a, b in zip(trans, alpha)], dtype=torch.float64)
    t_final = math.exp(-3.5)
    background = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    out = render_packed(tau, t, ray_idx, torch.tensor([6.0], dtype=torch.float64), background,
                        lambda sel, rays: colours if sel is None else colours[sel])
    torch.testing.assert_close(out.weights, w, rtol=1e-14, atol=0)
    torch.testing.assert_close(out.acc, torch.tensor([1 - t_final], dtype=torch.float64))
    torch.testing.assert_close(out.rgb[0], (w[:, None] * colours).sum(0) + t_final * background)
    torch.testing.assert_close(out.depth[0], (w * t).sum() + t_final * 6.0)


def test_render_packed_colour_threshold_skips_only_light_samples():
    """Samples at or below ``color_thres`` are never coloured; the rest composite as without the threshold."""
    tau = torch.tensor([1e-6, 0.3, 1e-6, 0.2, 8.0, 1.0], dtype=torch.float64)  # the last one is behind an opaque one
    t = torch.arange(6, dtype=torch.float64)
    ray_idx = torch.tensor([0, 0, 0, 1, 1, 1])
    colours = torch.rand(6, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    asked = []

    def rgb_fn(sel, rays):
        asked.append(None if sel is None else sel.tolist())
        return colours if sel is None else colours[sel]

    far, bg = torch.full((2,), 6.0, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
    full = render_packed(tau, t, ray_idx, far, bg, rgb_fn)
    thres = 1e-3
    cut = render_packed(tau, t, ray_idx, far, bg, rgb_fn, color_thres=thres)
    heavy = (full.weights > thres).nonzero()[:, 0].tolist()
    assert asked == [None, heavy] and heavy == [1, 3, 4]
    light = full.weights.clone()
    light[heavy] = 0
    dropped = torch.zeros(2, 3, dtype=torch.float64).index_add(0, ray_idx, light[:, None] * colours)
    torch.testing.assert_close(cut.rgb, full.rgb - dropped)
    torch.testing.assert_close(cut.acc, full.acc)


def test_render_packed_gradients_float64():
    g = torch.Generator().manual_seed(3)
    ray_idx = torch.tensor([0, 0, 1, 1, 1, 3])
    t = torch.rand(6, generator=g, dtype=torch.float64).cumsum(0)
    tau = (torch.rand(6, generator=g, dtype=torch.float64) * 2).requires_grad_()
    colours = torch.rand(6, 3, generator=g, dtype=torch.float64).requires_grad_()
    far = torch.full((4,), 9.0, dtype=torch.float64)
    bg = torch.ones(3, dtype=torch.float64)

    def run(tau_, colours_):
        out = render_packed(tau_, t, ray_idx, far, bg, lambda sel, rays: colours_)
        return out.rgb, out.acc, out.depth

    torch.autograd.gradcheck(run, (tau, colours))
    rgb, acc, _ = run(tau, colours)
    assert rgb[2].tolist() == [1.0, 1.0, 1.0] and acc[2] == 0.0  # a ray without samples shows the background


def _distortion_reference(w, s, ds):
    """mip-NeRF 360's eq. 15 for one ray, O(n^2), float64."""
    pair = sum(w[i] * w[j] * abs(s[i] - s[j]) for i in range(len(w)) for j in range(len(w)))
    return pair + sum(w[i] ** 2 * ds[i] for i in range(len(w))) / 3.0


def test_packed_distortion_equals_the_pairwise_definition():
    g = torch.Generator().manual_seed(3)
    counts = [0, 1, 4, 7]  # a ray without samples, a lone sample, two longer rays
    ray_idx = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    w = torch.rand(len(ray_idx), generator=g, dtype=torch.float64) * 0.3
    ds = torch.rand(len(ray_idx), generator=g, dtype=torch.float64) * 0.1 + 0.01
    s = torch.cat([torch.cumsum(ds[ray_idx == r], 0) for r in range(len(counts))])
    got = packed_distortion(w.float(), s.float(), ds.float(), ray_idx, len(counts))
    for r in range(len(counts)):
        sel = ray_idx == r
        want = _distortion_reference(w[sel].tolist(), s[sel].tolist(), ds[sel].tolist()) if sel.any() else 0.0
        assert got[r].item() == pytest.approx(want, rel=1e-6, abs=1e-9)
    assert got[1].item() == pytest.approx(w[0].item() ** 2 * ds[0].item() / 3.0, rel=1e-6)  # a lone sample: its own term


def test_packed_distortion_is_smaller_for_concentrated_weight_and_has_exact_gradients():
    s = torch.linspace(0.05, 0.95, 10, dtype=torch.float64)
    ds = torch.full_like(s, 0.1)
    ray_idx = torch.zeros(10, dtype=torch.long)
    spread = torch.full_like(s, 0.08)
    peaked = torch.zeros_like(s)
    peaked[4] = 0.8
    assert packed_distortion(peaked, s, ds, ray_idx, 1) < 0.2 * packed_distortion(spread, s, ds, ray_idx, 1)
    w = torch.rand(10, dtype=torch.float64, generator=torch.Generator().manual_seed(0)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: packed_distortion(x, s, ds, ray_idx, 1), (w,))
