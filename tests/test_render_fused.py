"""The compositor's fused CPU kernels (numba) against PyTorch's ops and float64 references."""

from __future__ import annotations

import pytest
import torch

from broken_numba import kernel_that_cannot_compile

from nerfmeta.fused import fused_kernels
from nerfmeta.render import volume
from nerfmeta.render.volume import fused_compositing, packed_weights, render_packed

needs_numba = pytest.mark.skipif(not fused_compositing(), reason="numba is not installed (the fused kernels are optional)")


def _packed(counts: list[int], seed: int, dtype: torch.dtype, scale: float = 2.0):
    """Random packed rays: ``counts[r]`` samples for ray r (0 allowed), optical depths, distances and colours."""
    g = torch.Generator().manual_seed(seed)
    ray_idx = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    m = ray_idx.numel()
    tau = torch.rand(m, generator=g, dtype=dtype) * scale
    t = torch.rand(m, generator=g, dtype=dtype).cumsum(0)
    colours = torch.rand(m, 3, generator=g, dtype=dtype)
    return tau, t, ray_idx, colours


def _render(tau, t, ray_idx, colours, thres: float, fused: bool):
    """render_packed's outputs and the gradients of a loss over all of them, on one path."""
    n = int(ray_idx.max()) + 2 if ray_idx.numel() else 3  # one ray past the last has no samples
    tau, colours = tau.clone().requires_grad_(), colours.clone().requires_grad_()
    far, bg = torch.full((n,), 50.0, dtype=tau.dtype), torch.tensor([0.2, 0.5, 0.9], dtype=tau.dtype)
    with fused_kernels(fused):
        out = render_packed(tau, t, ray_idx, far, bg, lambda sel, rays: colours if sel is None else colours[sel],
                            color_thres=thres)
        loss = (out.rgb * torch.arange(1.0, 4.0, dtype=tau.dtype)).sum() + out.depth.sin().sum() \
            + out.acc.square().sum() + (out.weights * torch.linspace(-1, 1, len(out.weights), dtype=tau.dtype)).sum()
        loss.backward()
    return [out.rgb, out.acc, out.depth, out.weights, tau.grad, colours.grad], out


@needs_numba
@pytest.mark.parametrize("thres", [0.0, 0.05])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fused_compositing_matches_pytorch_values_and_gradients(dtype, thres):
    tau, t, ray_idx, colours = _packed([5, 0, 1, 17, 3, 0, 40, 2], 0, dtype)
    fused, out = _render(tau, t, ray_idx, colours, thres, True)
    plain, _ = _render(tau, t, ray_idx, colours, thres, False)
    assert out.weights.grad_fn.name() == "_PackedWeightsBackward"  # the kernels really ran
    tol = {"rtol": 1e-12, "atol": 1e-12} if dtype == torch.float64 else {"rtol": 1e-5, "atol": 1e-6}
    for a, b in zip(fused, plain):
        torch.testing.assert_close(a, b, **tol)


@needs_numba
def test_fused_weights_against_a_float64_reference_on_stiff_rays():
    """Optical depths from 0 and 1e-12 to 1e16 (sigma up to 1e6 over steps up to 1e10): the kernels' float32 weights
    and gradients against the float64 ray by ray definition; every weight in [0, 1], a ray's sum 1 - T_final."""
    tau64 = torch.tensor([0.0, 1e-12, 3e-7, 0.5, 1e16, 2.0,   1e-12, 1e-12, 0.0,   40.0, 1e4, 0.3], dtype=torch.float64)
    ray_idx = torch.tensor([0, 0, 0, 0, 0, 0, 1, 1, 1, 2, 2, 2])
    grad_w = torch.linspace(-1.0, 2.0, 12, dtype=torch.float64)
    grad_t = torch.tensor([0.7, -0.3, 1.1], dtype=torch.float64)

    def reference(tau):
        w, t_final = [], []
        for r in range(3):
            x = tau[ray_idx == r]
            before = torch.cat([x.new_zeros(1), x.cumsum(0)[:-1]])
            w.append(torch.exp(-before) * -torch.expm1(-x))
            t_final.append(torch.exp(-x.sum()))
        return torch.cat(w), torch.stack(t_final)

    leaf = tau64.clone().requires_grad_()
    w_ref, t_ref = reference(leaf)
    (ref_grad,) = torch.autograd.grad((w_ref * grad_w).sum() + (t_ref * grad_t).sum(), leaf)
    tau32 = tau64.float().requires_grad_()
    w, t_final = packed_weights(tau32, ray_idx, 3)
    assert w.grad_fn.name() == "_PackedWeightsBackward"
    (grad,) = torch.autograd.grad((w * grad_w.float()).sum() + (t_final * grad_t.float()).sum(), tau32)
    torch.testing.assert_close(w.double(), w_ref.detach(), rtol=1e-6, atol=1e-30)
    torch.testing.assert_close(t_final.double(), t_ref.detach(), rtol=1e-6, atol=1e-30)
    torch.testing.assert_close(grad.double(), ref_grad, rtol=1e-5, atol=1e-6)
    assert torch.isfinite(grad).all() and bool(((w >= 0) & (w <= 1)).all())
    sums = torch.zeros(3).index_add(0, ray_idx, w) + t_final
    torch.testing.assert_close(sums, torch.ones(3), rtol=0, atol=1e-6)


@needs_numba
def test_second_derivatives_pass_through_the_fused_compositor():
    """MAML differentiates the gradient: the fused path's backward is itself differentiable (through PyTorch's ops)."""
    tau, t, ray_idx, colours = _packed([3, 0, 4, 2], 1, torch.float64)
    far, bg = torch.full((4,), 9.0, dtype=torch.float64), torch.ones(3, dtype=torch.float64)

    def run(tau_, colours_):
        out = render_packed(tau_, t, ray_idx, far, bg, lambda sel, rays: colours_ if sel is None else colours_[sel],
                            color_thres=0.05)
        return out.rgb, out.depth, out.weights

    inputs = (tau.requires_grad_(), colours.requires_grad_())
    assert run(*inputs)[0].grad_fn is not None
    torch.autograd.gradcheck(run, inputs)
    torch.autograd.gradgradcheck(run, inputs)


@needs_numba
def test_a_batch_without_samples_and_renders_without_gradients():
    empty = torch.zeros(0, dtype=torch.float32)
    ray_idx = torch.zeros(0, dtype=torch.int64)
    out = render_packed(empty, empty, ray_idx, torch.full((2,), 3.0), torch.tensor([0.1, 0.2, 0.3]),
                        lambda sel, rays: torch.zeros(0, 3), color_thres=1e-3)
    torch.testing.assert_close(out.rgb, torch.tensor([[0.1, 0.2, 0.3]] * 2))
    assert out.acc.tolist() == [0.0, 0.0] and out.depth.tolist() == [3.0, 3.0]
    tau, t, ray_idx, colours = _packed([4, 6], 2, torch.float32)
    with torch.no_grad():
        fast = render_packed(tau, t, ray_idx, torch.full((2,), 9.0), torch.ones(3), lambda sel, rays: colours)
        with fused_kernels(False):
            slow = render_packed(tau, t, ray_idx, torch.full((2,), 9.0), torch.ones(3), lambda sel, rays: colours)
    torch.testing.assert_close(fast.rgb, slow.rgb, rtol=1e-5, atol=1e-6)


@needs_numba
def test_a_numba_that_cannot_compile_means_the_pytorch_path_with_a_warning(monkeypatch):
    from nerfmeta.render import _volume_numba

    with kernel_that_cannot_compile(monkeypatch, _volume_numba, "weights_forward"):
        with pytest.warns(UserWarning, match="numba could not compile the compositing kernels .*no LLVM target"):
            assert not fused_compositing()
        tau, t, ray_idx, colours = _packed([3, 2], 3, torch.float64)
        w, _ = packed_weights(tau.requires_grad_(), ray_idx, 2)
        assert w.grad_fn.name() != "_PackedWeightsBackward"
    assert fused_compositing() and volume._kernels() is not None


def test_every_backbone_loads_the_renderers_kernels_before_a_fits_clock(monkeypatch):
    """``warm_up`` (called by ``run_fit`` before the clock) loads the compositor's, the contraction's and the march's
    kernels, and the grid's the learned start's."""
    from nerfmeta import fused
    from nerfmeta.fields.registry import BACKBONES

    for backbone, (_, cls, _) in BACKBONES.items():
        asked = []
        monkeypatch.setattr(fused, "load", lambda module, smoke, what: asked.append(module))
        cls.warm_up()
        monkeypatch.undo()
        assert {"nerfmeta.render._volume_numba", "nerfmeta.render._contraction_numba",
                "nerfmeta.render._march_numba"} <= set(asked), backbone
        # the grid's also the learned start's, which the default route builds a grid with before the fit's clock
        assert ("nerfmeta.priors._features_numba" in asked) == (backbone == "grid"), backbone


@needs_numba
def test_the_weighted_sums_are_right_for_rays_in_any_order():
    """The colour and depth sums add a run of one ray's samples at a time, so interleaved rays sum as index_add does."""
    g = torch.Generator().manual_seed(6)
    ray_idx = torch.tensor([2, 2, 0, 0, 0, 2, 1, 0])
    weights, t = torch.rand(8, generator=g, dtype=torch.float64), torch.rand(8, generator=g, dtype=torch.float64)
    colours = torch.rand(8, 3, generator=g, dtype=torch.float64)
    sel = torch.tensor([0, 2, 3, 5, 7])
    ray_c = ray_idx[sel]
    fast = volume._WeightedSums.apply(weights, colours[sel], sel, ray_c, ray_idx, t, 4)
    slow = volume._weighted_sums_torch(weights, colours[sel], sel, ray_c, ray_idx, t, 4)
    for a, b in zip(fast, slow):
        torch.testing.assert_close(a, b, rtol=1e-14, atol=1e-14)
