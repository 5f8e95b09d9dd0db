"""Image quality metrics: MSE, PSNR and SSIM.

Pure functions over tensors; device and dtype follow the inputs. Images are channel-last, as
everywhere in nerfmeta: ``(H, W, C)`` or ``(N, H, W, C)``, values in ``[0, data_range]``.
Ray colours are ``(n_rays, 3)``.

Reductions: by default every metric is one number for the whole input (the mean over all
pixels, channels and images). ``per_image=True`` gives one value per image, ``(N,)`` for a batch
(``()`` for a single image). NeRF papers report the mean over test images of the per-image
PSNR, which is not the PSNR of the mean MSE: ``psnr(..., per_image=True).mean()``.
"""

from __future__ import annotations

import math
from typing import overload

import torch
import torch.nn.functional as F

__all__ = [
    "mse",
    "mse_to_psnr",
    "psnr",
    "psnr_to_mse",
    "ssim",
    "ssim_skip_reason",
]


# --------------------------------------------------------------------------------------------
# MSE and PSNR
# --------------------------------------------------------------------------------------------


def _check_pair(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.shape != target.shape:
        raise ValueError(
            f"pred and target must have the same shape, got {tuple(pred.shape)} and "
            f"{tuple(target.shape)}"
        )


def _check_data_range(data_range: float) -> None:
    if not data_range > 0:
        raise ValueError(f"data_range must be positive, got {data_range}")


def _image_dims(x: torch.Tensor, per_image: bool) -> tuple[int, ...]:
    """Dimensions to average over: all of them, or the last three (H, W, C) per image."""
    if not per_image:
        return tuple(range(x.ndim))
    if x.ndim not in (3, 4):
        raise ValueError(
            f"per_image needs (H, W, C) or (N, H, W, C) images, got shape {tuple(x.shape)}"
        )
    return (-3, -2, -1)


def mse(pred: torch.Tensor, target: torch.Tensor, *, per_image: bool = False) -> torch.Tensor:
    """Mean squared error.

    Cheap and differentiable: this is the photometric loss of the fit loop on ray colours.

    Args:
        pred: (..., C) predicted colours: ray batch (n_rays, C), image (H, W, C) or batch of
            images (N, H, W, C).
        target: same shape as ``pred``.
        per_image: return one value per image instead of the mean over everything. Needs
            (H, W, C) or (N, H, W, C) inputs.

    Returns:
        () mean over all elements, or with ``per_image`` (N,) for a batch, () for one image.
    """
    _check_pair(pred, target)
    if not per_image:
        return F.mse_loss(pred, target)
    return (pred - target).square().mean(dim=_image_dims(pred, per_image))


@overload
def mse_to_psnr(mse: torch.Tensor, data_range: float = 1.0) -> torch.Tensor: ...
@overload
def mse_to_psnr(mse: float, data_range: float = 1.0) -> float: ...


def mse_to_psnr(mse: torch.Tensor | float, data_range: float = 1.0) -> torch.Tensor | float:
    """PSNR in dB from a mean squared error: ``10 log10(data_range**2 / mse)``.

    For ``data_range = 1`` this is ``-10 log10(mse)``. An MSE of 0 (a perfect match) gives
    ``+inf``, never NaN; a negative tensor MSE gives NaN (the tensor path does not inspect
    values, so it never synchronises with the device). The gradient at MSE 0 is ``-inf``: use
    the MSE, not the PSNR, as a loss.

    Args:
        mse: a tensor of any shape, or a Python float.
        data_range: the difference between the largest and smallest possible pixel value.

    Returns:
        PSNR of the same shape, dtype and device as ``mse``; a float for a float.
    """
    _check_data_range(data_range)
    offset = 20.0 * math.log10(data_range)
    if isinstance(mse, torch.Tensor):
        # log10(0) = -inf, so a zero MSE maps to +inf without special-casing.
        out = -10.0 * torch.log10(mse)
        return out + offset if offset != 0.0 else out
    mse = float(mse)
    if mse < 0 or math.isnan(mse):
        raise ValueError(f"MSE must be non-negative, got {mse}")
    if mse == 0.0:
        return math.inf
    return offset - 10.0 * math.log10(mse)


@overload
def psnr_to_mse(psnr: torch.Tensor, data_range: float = 1.0) -> torch.Tensor: ...
@overload
def psnr_to_mse(psnr: float, data_range: float = 1.0) -> float: ...


def psnr_to_mse(psnr: torch.Tensor | float, data_range: float = 1.0) -> torch.Tensor | float:
    """Mean squared error from a PSNR in dB, the inverse of :func:`mse_to_psnr`.

    ``+inf`` dB maps back to an MSE of 0.

    Args:
        psnr: a tensor of any shape, or a Python float.
        data_range: the difference between the largest and smallest possible pixel value.

    Returns:
        MSE of the same shape, dtype and device as ``psnr``; a float for a float.
    """
    _check_data_range(data_range)
    scale = data_range**2
    if isinstance(psnr, torch.Tensor):
        out = torch.pow(10.0, psnr / -10.0)
        return out * scale if scale != 1.0 else out
    return scale * 10.0 ** (float(psnr) / -10.0)


def psnr(
    pred: torch.Tensor,
    target: torch.Tensor,
    data_range: float = 1.0,
    *,
    per_image: bool = False,
) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB, ``10 log10(data_range**2 / mse)``.

    Differentiable (except at a perfect match, where it is ``+inf``) and cheap enough to log
    every iteration of the fit loop on ray colours.

    Args:
        pred: (..., C) ray colours (n_rays, C), an image (H, W, C) or images (N, H, W, C).
        target: same shape as ``pred``.
        data_range: the difference between the largest and smallest possible pixel value.
        per_image: one PSNR per image instead of the PSNR of the MSE over everything.

    Returns:
        () or, with ``per_image``, (N,) for a batch and () for one image.
    """
    return mse_to_psnr(mse(pred, target, per_image=per_image), data_range)


# --------------------------------------------------------------------------------------------
# SSIM
# --------------------------------------------------------------------------------------------


def _compute_dtype(pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.dtype, torch.dtype]:
    """(dtype of the result, dtype to compute in): half precisions are computed in float32."""
    dtype = torch.promote_types(pred.dtype, target.dtype)
    if not dtype.is_floating_point:
        raise TypeError(
            f"SSIM needs floating-point images, got {dtype}; convert them with .float() "
            "(and divide by 255 or pass data_range=255 for 8-bit images)"
        )
    compute = dtype if dtype in (torch.float32, torch.float64) else torch.float32
    return dtype, compute


def _gaussian_window(window: int, sigma: float, dtype: torch.dtype, device) -> torch.Tensor:
    """(window,) normalised Gaussian taps centred on the middle tap (computed in float64)."""
    x = torch.arange(window, dtype=torch.float64) - (window - 1) / 2
    taps = torch.exp(-0.5 * (x / sigma) ** 2)
    return (taps / taps.sum()).to(device=device, dtype=dtype)


SSIM_WINDOW = 11
"""Gaussian taps of :func:`ssim`'s default window (mip-NeRF / JAXNeRF): images need at least this many pixels per side."""


def ssim_skip_reason(height: int, width: int, window: int = SSIM_WINDOW) -> str | None:
    """Why :func:`ssim` cannot score ``height`` x ``width`` images with ``window``, or None when it can.

    Callers decide with this before a long job (a fit) rather than failing after it.
    """
    if height >= window and width >= window:
        return None
    return (f"SSIM skipped: the images are {width}x{height} pixels, smaller than its {window}x{window} window "
            "(use larger images or a smaller --downscale to get SSIM)")


def ssim(
    pred: torch.Tensor,
    target: torch.Tensor,
    data_range: float = 1.0,
    window: int = SSIM_WINDOW,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
    *,
    per_image: bool = False,
) -> torch.Tensor:
    """Structural similarity as computed in NeRF papers (mip-NeRF / JAXNeRF ``compute_ssim``).

    Each channel is blurred separably with a ``window``-tap Gaussian of std ``sigma`` using a
    *valid* convolution (no padding), the SSIM map is formed from the local means, variances and
    covariance (population statistics, as in Wang et al. 2004), and the map is averaged over the
    valid region ``(H - window + 1, W - window + 1)`` and the channels. As in JAXNeRF, variances
    are clipped at 0 and the covariance to ``[-sqrt(var0 var1), sqrt(var0 var1)]``; this only
    changes round-off-sized values, and the clip bound is treated as a constant in the backward
    pass so that gradients stay finite in flat regions (SSIM can be used in a loss).

    Agreement with ``skimage.metrics.structural_similarity(a, b, gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)``: skimage filters
    with reflect padding and then crops ``(win_size - 1) // 2`` pixels from every border, which
    keeps exactly the pixels whose window never touches the padding, i.e. the same valid region.
    Its Gaussian has radius ``int(3.5 * sigma + 0.5)`` (``truncate=3.5``), so ``win_size`` is 11
    for ``sigma=1.5`` and the two agree to round-off (below 1e-6 in float32, 1e-12 in float64;
    measured in ``tests/test_metrics.py``). For other ``sigma`` they agree only when
    ``window == 2 * int(3.5 * sigma + 0.5) + 1``: skimage ignores ``win_size`` when sizing its
    Gaussian, while here (as in JAXNeRF) ``window`` and ``sigma`` are independent. skimage does
    not clip the (co)variances.

    Args:
        pred: (H, W, C) or (N, H, W, C) images in ``[0, data_range]``, any float dtype;
            ``H`` and ``W`` must be at least ``window``.
        target: same shape as ``pred``.
        data_range: the difference between the largest and smallest possible pixel value.
        window: odd number of Gaussian taps.
        sigma: standard deviation of the Gaussian, in pixels.
        k1, k2: the stabilising constants ``C1 = (k1 * data_range)**2``,
            ``C2 = (k2 * data_range)**2``.
        per_image: one SSIM per image instead of the mean over images.

    Returns:
        () or, with ``per_image``, (N,) for a batch and () for one image, in the promoted dtype
        of the inputs (float16/bfloat16 are computed in float32 and the result cast back).
    """
    _check_pair(pred, target)
    _check_data_range(data_range)
    if pred.ndim not in (3, 4):
        raise ValueError(f"SSIM needs (H, W, C) or (N, H, W, C) images, got {tuple(pred.shape)}")
    if window < 1 or window % 2 != 1:
        raise ValueError(f"SSIM window must be a positive odd number of pixels, got {window}")
    if sigma <= 0:
        raise ValueError(f"SSIM sigma must be positive, got {sigma}")
    height, width, channels = pred.shape[-3:]
    if height < window or width < window:
        raise ValueError(
            f"SSIM needs images at least {window}x{window} pixels (the window), got "
            f"{height}x{width}; pass a smaller odd window for tiny images"
        )
    out_dtype, dtype = _compute_dtype(pred, target)

    single = pred.ndim == 3
    x = pred.to(dtype)
    y = target.to(dtype)
    if single:
        x, y = x.unsqueeze(0), y.unsqueeze(0)
    n = x.shape[0]
    # (N, H, W, C) -> (N * C, 1, H, W): every channel of every image is blurred on its own.
    x = x.permute(0, 3, 1, 2).reshape(n * channels, 1, height, width)
    y = y.permute(0, 3, 1, 2).reshape(n * channels, 1, height, width)

    # The five maps to blur, as the channels of one image: a depthwise (grouped) convolution is
    # an order of magnitude faster on CPU than a batch of single-channel ones.
    stats = torch.cat([x, y, x * x, y * y, x * y], dim=0).reshape(1, -1, height, width)
    groups = stats.shape[1]
    taps = _gaussian_window(window, sigma, dtype, x.device)
    stats = F.conv2d(stats, taps.view(1, 1, window, 1).expand(groups, 1, window, 1), groups=groups)
    stats = F.conv2d(stats, taps.view(1, 1, 1, window).expand(groups, 1, 1, window), groups=groups)
    mu_x, mu_y, e_xx, e_yy, e_xy = stats.reshape(-1, *stats.shape[-2:]).chunk(5, dim=0)

    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    var_x = (e_xx - mu_xx).clamp_min(0.0)
    var_y = (e_yy - mu_yy).clamp_min(0.0)
    # |cov| <= sqrt(var_x var_y) holds exactly; the clip only removes round-off. Detaching the
    # bound keeps sqrt's infinite slope at 0 (flat patches) out of the backward pass.
    bound = torch.sqrt(var_x * var_y).detach()
    cov = torch.clamp(e_xy - mu_xy, min=-bound, max=bound)

    c1 = (k1 * data_range) ** 2
    c2 = (k2 * data_range) ** 2
    numer = (2.0 * mu_xy + c1) * (2.0 * cov + c2)
    denom = (mu_xx + mu_yy + c1) * (var_x + var_y + c2)
    ssim_map = (numer / denom).reshape(n, channels, height - window + 1, width - window + 1)

    per = ssim_map.mean(dim=(1, 2, 3))
    if single:
        per = per[0]
    out = per if per_image else per.mean()
    return out.to(out_dtype)
