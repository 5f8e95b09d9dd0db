"""Image metrics: exact small cases, PSNR/MSE round trip, SSIM against skimage."""

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from nerfmeta.metrics import (
    mse,
    mse_to_psnr,
    psnr,
    psnr_to_mse,
    ssim,
)


# ------------------------------------------------------------------------------ MSE and PSNR


@pytest.mark.parametrize("shape", [(64, 3), (5, 7, 3), (2, 5, 7, 3)])
def test_constant_error_of_0_1_is_20_db(shape):
    target = torch.zeros(shape, dtype=torch.float64)
    pred = target + 0.1
    assert mse(pred, target).item() == pytest.approx(0.01, rel=1e-14)
    assert psnr(pred, target).item() == pytest.approx(20.0, abs=1e-12)
    # float32: 0.1 is not representable, but the answer is 20 dB to float32 precision
    assert psnr(pred.float(), target.float()).item() == pytest.approx(20.0, abs=1e-5)


def test_psnr_with_data_range_255():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(2, 6, 5, 3, generator=g, dtype=torch.float64).unbind(0)
    scaled = psnr(a * 255, b * 255, data_range=255.0)
    torch.testing.assert_close(scaled, psnr(a, b), rtol=0, atol=1e-12)
    assert mse_to_psnr(255.0**2 * 0.01, data_range=255.0) == pytest.approx(20.0, abs=1e-12)


def test_zero_mse_gives_inf_not_nan():
    x = torch.rand(4, 4, 3)
    assert psnr(x, x).item() == math.inf
    assert mse_to_psnr(torch.tensor(0.0)).item() == math.inf
    assert mse_to_psnr(0.0) == math.inf
    assert mse_to_psnr(0) == math.inf
    assert psnr_to_mse(math.inf) == 0.0
    assert psnr_to_mse(torch.tensor(math.inf)).item() == 0.0
    per = psnr(torch.stack([x, x + 0.1]), torch.stack([x, x]), per_image=True)
    assert per[0].item() == math.inf and per[1].item() == pytest.approx(20.0, abs=1e-4)
    with pytest.raises(ValueError, match="non-negative"):
        mse_to_psnr(-1.0)


def test_psnr_mse_round_trip_over_many_values():
    g = torch.Generator().manual_seed(0)
    m = 10.0 ** torch.empty(10_000, dtype=torch.float64).uniform_(-12, 2, generator=g)
    torch.testing.assert_close(psnr_to_mse(mse_to_psnr(m)), m, rtol=1e-12, atol=0)
    p = torch.empty(10_000, dtype=torch.float64).uniform_(-20, 120, generator=g)
    torch.testing.assert_close(mse_to_psnr(psnr_to_mse(p)), p, rtol=0, atol=1e-11)
    for value in m[:200].tolist():  # the float path agrees with the tensor path
        assert psnr_to_mse(mse_to_psnr(value)) == pytest.approx(value, rel=1e-12)
        as_tensor = mse_to_psnr(torch.tensor(value, dtype=torch.float64)).item()
        assert mse_to_psnr(value) == pytest.approx(as_tensor, abs=1e-12)
    for r in (1.0, 2.0, 255.0):
        torch.testing.assert_close(psnr_to_mse(mse_to_psnr(m, r), r), m, rtol=1e-12, atol=0)
    m32 = m.float().clamp_min(1e-30)
    torch.testing.assert_close(psnr_to_mse(mse_to_psnr(m32)), m32, rtol=2e-5, atol=0)
    assert mse_to_psnr(m32).dtype == torch.float32


def test_per_image_reduction():
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(2, 3, 8, 9, 3, generator=g, dtype=torch.float64).unbind(0)
    per = mse(a, b, per_image=True)
    assert per.shape == (3,)
    for i in range(3):
        assert per[i].item() == pytest.approx(((a[i] - b[i]) ** 2).mean().item(), rel=1e-14)
    assert mse(a, b).item() == pytest.approx(per.mean().item(), rel=1e-14)  # equal-size images
    assert psnr(a[0], b[0], per_image=True).shape == ()
    with pytest.raises(ValueError, match="per_image"):
        mse(torch.rand(10, 3), torch.rand(10, 3), per_image=True)
    with pytest.raises(ValueError, match="same shape"):
        mse(torch.rand(10, 3), torch.rand(10, 1))


def test_psnr_gradient_is_finite_and_matches_hand_formula():
    g = torch.Generator().manual_seed(2)
    target = torch.rand(256, 3, generator=g, dtype=torch.float64)
    pred = (target + 0.05 * torch.randn(256, 3, generator=g, dtype=torch.float64)).requires_grad_()
    psnr(pred, target).backward()
    diff = (pred - target).detach()
    m = (diff**2).mean()
    expected = -10.0 / math.log(10.0) / m * 2.0 * diff / diff.numel()
    assert torch.isfinite(pred.grad).all()
    torch.testing.assert_close(pred.grad, expected, rtol=1e-12, atol=0)
    # float32 ray batch, as in the fit loop
    pred32 = pred.detach().float().requires_grad_()
    psnr(pred32, target.float()).backward()
    assert torch.isfinite(pred32.grad).all()


# ------------------------------------------------------------------------------------- SSIM


def _skimage_ssim(a: np.ndarray, b: np.ndarray) -> float:
    return structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
        data_range=1.0, channel_axis=-1,
    )


def _image_pairs(seed: int, h: int, w: int):
    """Independent noise, a noisy copy, and a structured image with a flat block and edges."""
    rng = np.random.default_rng(seed)
    a = rng.random((h, w, 3))
    yield "independent", a, rng.random((h, w, 3))
    yield "noisy copy", a, np.clip(a + 0.05 * rng.standard_normal(a.shape), 0, 1)
    yy, xx = np.mgrid[0:h, 0:w]
    s = 0.5 + 0.4 * np.sin(xx / 3.0 + seed)[..., None] * np.cos(yy / 5.0)[..., None] * np.ones(3)
    s[: h // 2, : w // 2] = 0.25  # exactly flat: zero variance, the clipping path
    s[h // 2 :, w // 2 :] = (xx[h // 2 :, w // 2 :] % 4 < 2)[..., None]  # hard edges
    t = s.copy()
    noise = 0.03 * rng.standard_normal(t[h // 3 :, :].shape)
    t[h // 3 :, :] = np.clip(t[h // 3 :, :] + noise, 0, 1)
    yield "structured", s, t


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("size", [(37, 53), (11, 11), (12, 11), (11, 30), (13, 17), (48, 48)])
def test_ssim_matches_skimage(seed, size):
    for name, a, b in _image_pairs(seed, *size):
        ref = _skimage_ssim(a, b)
        ours64 = ssim(torch.from_numpy(a), torch.from_numpy(b))
        assert ours64.dtype == torch.float64
        assert ours64.item() == pytest.approx(ref, abs=1e-10), name
        ours32 = ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float())
        assert ours32.dtype == torch.float32
        assert ours32.item() == pytest.approx(ref, abs=1e-5), name


def test_ssim_batch_is_the_mean_of_per_image_values():
    pairs = list(_image_pairs(3, 20, 24))
    a = torch.from_numpy(np.stack([p[1] for p in pairs]))
    b = torch.from_numpy(np.stack([p[2] for p in pairs]))
    per = ssim(a, b, per_image=True)
    assert per.shape == (3,)
    for i, (_, ai, bi) in enumerate(pairs):
        assert per[i].item() == pytest.approx(_skimage_ssim(ai, bi), abs=1e-10)
    assert ssim(a, b).item() == pytest.approx(per.mean().item(), abs=1e-14)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16])
def test_ssim_of_identical_images_is_one_and_ssim_is_symmetric(dtype):
    g = torch.Generator().manual_seed(4)
    x = torch.rand(2, 16, 19, 3, generator=g).to(dtype)
    y = (x.float() + 0.1 * torch.rand(2, 16, 19, 3, generator=g)).clamp(0, 1).to(dtype)
    assert ssim(x, x).item() == 1.0
    assert ssim(x, x).dtype == dtype
    torch.testing.assert_close(ssim(x, y), ssim(y, x), rtol=0, atol=1e-12)
    assert ssim(x, y).item() < 1.0
    if dtype in (torch.float16, torch.bfloat16):  # computed in float32, rounded on return
        assert ssim(x, y).item() == pytest.approx(ssim(x.float(), y.float()).item(), abs=1e-2)


def test_ssim_gradient_is_finite_even_on_flat_images():
    g = torch.Generator().manual_seed(5)
    target = torch.full((24, 24, 3), 0.5, dtype=torch.float64)
    target[12:, :] = torch.rand(12, 24, 3, generator=g, dtype=torch.float64)
    for pred in (target.clone(), torch.full_like(target, 0.5), target + 0.01):
        pred = pred.requires_grad_()
        ssim(pred, target).backward()
        assert torch.isfinite(pred.grad).all()


def test_ssim_rejects_bad_inputs():
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(torch.rand(10, 20, 3), torch.rand(10, 20, 3))
    with pytest.raises(ValueError, match="odd"):
        ssim(torch.rand(20, 20, 3), torch.rand(20, 20, 3), window=10)
    with pytest.raises(TypeError, match="floating-point"):
        ssim(torch.zeros(20, 20, 3, dtype=torch.uint8), torch.zeros(20, 20, 3, dtype=torch.uint8))
    assert ssim(torch.rand(20, 20, 1), torch.rand(20, 20, 1), window=3, sigma=0.5).shape == ()


def test_ssim_skip_reason_names_the_size_and_the_window() -> None:
    from nerfmeta.metrics import ssim_skip_reason

    assert ssim_skip_reason(11, 11) is None and ssim_skip_reason(32, 11) is None
    assert "8x32 pixels, smaller than its 11x11 window" in ssim_skip_reason(32, 8)
    assert ssim_skip_reason(8, 8, window=7) is None and ssim_skip_reason(6, 8, window=7) is not None
    with pytest.raises(ValueError):  # the reason is exactly when ssim() would refuse
        ssim(torch.rand(10, 12, 3), torch.rand(10, 12, 3))
