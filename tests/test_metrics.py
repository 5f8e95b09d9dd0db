"""Image metrics: exact small cases, PSNR/MSE round trip, SSIM against skimage, LPIPS loading."""

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from nerfmeta.metrics import (
    LPIPS_NETWORKS,
    ImageMetrics,
    LpipsWeightsError,
    MetricUnavailable,
    evaluate_images,
    load_lpips,
    lpips,
    lpips_available,
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


# ------------------------------------------------------------------------------------ LPIPS


def test_lpips_is_unavailable_without_weights(tmp_path):
    ok, reason = lpips_available()
    assert not ok and "alex.pth" in reason and "alexnet-owt-7be5be79.pth" in reason
    ok, reason = lpips_available(tmp_path / "nowhere")
    assert not ok and "does not exist" in reason and str(tmp_path / "nowhere") in reason
    (tmp_path / "alex.pth").write_bytes(b"")
    ok, reason = lpips_available(tmp_path)
    assert not ok and "lacks alexnet-owt-7be5be79.pth" in reason and "lacks alex.pth" not in reason
    x = torch.rand(1, 32, 32, 3)
    with pytest.raises(MetricUnavailable, match="alexnet-owt-7be5be79.pth"):
        lpips(x, x, tmp_path)
    result = evaluate_images(x, x, lpips_weights=tmp_path)
    assert result.lpips is None and result.lpips_note == reason
    assert result.psnr == math.inf and result.ssim == 1.0
    result = evaluate_images(x, x)
    assert result.lpips is None and "no weights folder" in result.lpips_note


def _tv_features(builder: str):
    from nerfmeta.compat import import_torchvision

    with torch.device("meta"):
        return getattr(import_torchvision().models, builder)(weights=None).features


@pytest.fixture(scope="module")
def random_alex_weights(tmp_path_factory):
    """A weights folder in the documented layout, holding random weights."""
    spec = LPIPS_NETWORKS["alex"]
    folder = tmp_path_factory.mktemp("lpips_weights")
    g = torch.Generator().manual_seed(0)
    backbone = {}
    for key, meta in _tv_features(spec.builder).state_dict().items():
        fan_in = meta[0].numel() if meta.ndim > 1 else 1
        backbone[f"features.{key}"] = torch.randn(meta.shape, generator=g) * math.sqrt(2.0 / fan_in)
    backbone["classifier.6.bias"] = torch.zeros(1000)  # the real file has a classifier: ignored
    torch.save(backbone, folder / spec.backbone_file)
    linear = {
        f"lin{k}.model.1.weight": torch.rand(1, c, 1, 1, generator=g)  # non-negative, as trained
        for k, c in enumerate(spec.channels)
    }
    torch.save(linear, folder / spec.linear_file)
    return folder, backbone, linear


def _reference_lpips(x, y, backbone, linear):
    """LPIPS v0.1 written out layer by layer: taps after the ReLUs at 1, 4, 7, 9 and 11."""
    features = _tv_features("alexnet")
    state = {k[len("features.") :]: v for k, v in backbone.items() if k.startswith("features.")}
    features.load_state_dict(state, assign=True)
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def taps(img):
        h, out = (img.permute(0, 3, 1, 2) * 2 - 1 - shift) / scale, []
        for i, layer in enumerate(features[:12]):  # the final max-pool is not used
            h = layer(h)
            if i in (1, 4, 7, 9, 11):
                out.append(h / (h.pow(2).sum(1, keepdim=True).sqrt() + 1e-10))
        return out

    total = 0
    for k, (fx, fy) in enumerate(zip(taps(x), taps(y))):
        w = linear[f"lin{k}.model.1.weight"]
        total = total + ((fx - fy) ** 2 * w).sum(1).mean((1, 2))
    return total


def test_lpips_from_random_weights_in_the_expected_layout(random_alex_weights):
    folder, backbone, linear = random_alex_weights
    ok, note = lpips_available(folder)
    assert ok and "alex" in note
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 48, 40, 3, generator=g)
    y = (x + 0.2 * torch.randn(2, 48, 40, 3, generator=g)).clamp(0, 1)

    assert lpips(x, x, folder).item() == 0.0
    net = load_lpips(folder)
    d = lpips(x, y, net, per_image=True)
    assert d.shape == (2,) and (d > 0).all()
    with torch.no_grad():
        reference = _reference_lpips(x, y, backbone, linear)
    torch.testing.assert_close(d, reference, rtol=1e-5, atol=1e-7)
    assert lpips(x[0], y[0], net).item() == pytest.approx(d[0].item(), rel=1e-6)
    scaled = lpips(x * 255, y * 255, net, data_range=255.0)
    assert scaled.item() == pytest.approx(d.mean().item(), rel=1e-5)
    assert lpips(x.double(), y.double(), net).dtype == torch.float64

    result = evaluate_images(x, y, lpips_weights=folder)
    assert isinstance(result, ImageMetrics)
    assert result.lpips == pytest.approx(d.mean().item(), rel=1e-5) and "alex" in result.lpips_note
    assert result.psnr == pytest.approx(psnr(x, y, per_image=True).mean().item(), rel=1e-6)
    assert result.ssim == pytest.approx(ssim(x, y).item(), abs=1e-6)


def test_lpips_rejects_weights_that_do_not_fit(random_alex_weights, tmp_path):
    folder, backbone, linear = random_alex_weights
    spec = LPIPS_NETWORKS["alex"]
    (tmp_path / spec.backbone_file).symlink_to(folder / spec.backbone_file)
    torch.save({"lin0.model.1.weight": linear["lin0.model.1.weight"]}, tmp_path / spec.linear_file)
    with pytest.raises(LpipsWeightsError, match="lin4.model.1.weight"):
        load_lpips(tmp_path)
    bad = dict(linear, **{"lin2.model.1.weight": torch.rand(1, 7, 1, 1)})
    torch.save(bad, tmp_path / spec.linear_file)
    with pytest.raises(LpipsWeightsError, match=r"\(1, 384, 1, 1\)"):
        load_lpips(tmp_path)
    (tmp_path / spec.linear_file).write_bytes(b"not a checkpoint")
    with pytest.raises(LpipsWeightsError, match="cannot read"):
        evaluate_images(torch.rand(1, 32, 32, 3), torch.rand(1, 32, 32, 3), tmp_path)


def test_ssim_skip_reason_names_the_size_and_the_window() -> None:
    from nerfmeta.metrics import ssim_skip_reason

    assert ssim_skip_reason(11, 11) is None and ssim_skip_reason(32, 11) is None
    assert "8x32 pixels, smaller than its 11x11 window" in ssim_skip_reason(32, 8)
    assert ssim_skip_reason(8, 8, window=7) is None and ssim_skip_reason(6, 8, window=7) is not None
    with pytest.raises(ValueError):  # the reason is exactly when ssim() would refuse
        ssim(torch.rand(10, 12, 3), torch.rand(10, 12, 3))
