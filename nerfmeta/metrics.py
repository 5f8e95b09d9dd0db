"""Image quality metrics: MSE, PSNR, SSIM and (with local weights only) LPIPS.

Pure functions over tensors; device and dtype follow the inputs. Images are channel-last, as
everywhere in nerfmeta: ``(H, W, C)`` or ``(N, H, W, C)``, values in ``[0, data_range]``.
Ray colours are ``(n_rays, 3)``.

Reductions: by default every metric is one number for the whole input (the mean over all
pixels, channels and images). ``per_image=True`` gives one value per image, ``(N,)`` for a batch
(``()`` for a single image). NeRF papers report the mean over test images of the per-image
PSNR, which is not the PSNR of the mean MSE; :func:`evaluate_images` does the former.

LPIPS is computed only from weights the user already has on disk; nothing is ever downloaded.
See :func:`load_lpips` for the expected folder layout.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import overload

import torch
import torch.nn.functional as F
from torch import nn

from nerfmeta.errors import ConfigError, NerfmetaError

__all__ = [
    "ImageMetrics",
    "LPIPS_NETWORKS",
    "LpipsNetwork",
    "LpipsSpec",
    "LpipsWeightsError",
    "MetricUnavailable",
    "evaluate_images",
    "load_lpips",
    "lpips",
    "lpips_available",
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


# --------------------------------------------------------------------------------------------
# LPIPS (local weights only)
# --------------------------------------------------------------------------------------------


class MetricUnavailable(NerfmetaError):
    """A metric cannot be computed on this machine (e.g. its weights are not on disk)."""


class LpipsWeightsError(NerfmetaError):
    """An LPIPS weight file is present but cannot be read or does not fit the network."""


@dataclass(frozen=True)
class LpipsSpec:
    """The files and layout of one LPIPS v0.1 network.

    Attributes:
        name: network name as the ``lpips`` package spells it (``net=...``).
        linear_file: file name of the linear-layer weights, as shipped inside the ``lpips``
            package at ``lpips/weights/v0.1/<name>.pth``; keys ``lin{k}.model.1.weight``,
            each of shape (1, channels[k], 1, 1).
        backbone_file: file name of the torchvision ImageNet state dict, as torchvision caches
            it in ``~/.cache/torch/hub/checkpoints/`` (keys ``features.*``; ``classifier.*``
            may be present and is ignored).
        backbone_weights: the torchvision weights enum entry that file holds.
        builder: the ``torchvision.models`` builder whose ``features`` is the backbone.
        channels: channels of the features compared at each tap.
        slice_ends: the tapped features are the outputs of ``features[:end]`` for each end.
    """

    name: str
    linear_file: str
    backbone_file: str
    backbone_weights: str
    builder: str
    channels: tuple[int, ...]
    slice_ends: tuple[int, ...]


LPIPS_NETWORKS: dict[str, LpipsSpec] = {
    "alex": LpipsSpec(
        name="alex",
        linear_file="alex.pth",
        backbone_file="alexnet-owt-7be5be79.pth",
        backbone_weights="AlexNet_Weights.IMAGENET1K_V1",
        builder="alexnet",
        channels=(64, 192, 384, 256, 256),
        slice_ends=(2, 5, 8, 10, 12),
    ),
    "vgg": LpipsSpec(
        name="vgg",
        linear_file="vgg.pth",
        backbone_file="vgg16-397923af.pth",
        backbone_weights="VGG16_Weights.IMAGENET1K_V1",
        builder="vgg16",
        channels=(64, 128, 256, 512, 512),
        slice_ends=(4, 9, 16, 23, 30),
    ),
}
"""LPIPS v0.1 networks that can be loaded from local files (the ``lpips`` default is alex)."""

# The lpips package's ScalingLayer: inputs in [-1, 1] are shifted and scaled per channel.
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)


def _lpips_spec(net: str) -> LpipsSpec:
    try:
        return LPIPS_NETWORKS[net]
    except KeyError:
        raise ConfigError(
            f"unknown LPIPS network {net!r}; choose one of {', '.join(LPIPS_NETWORKS)}"
        ) from None


def _missing_weights_reason(weights_dir: str | os.PathLike | None, spec: LpipsSpec) -> str | None:
    """Why LPIPS-``spec.name`` cannot be loaded from ``weights_dir``, or None if it can."""
    expected = (
        f"{spec.linear_file} (from the lpips package: lpips/weights/v0.1/{spec.linear_file}) "
        f"and {spec.backbone_file} (torchvision {spec.backbone_weights}, as cached in "
        "~/.cache/torch/hub/checkpoints/)"
    )
    if weights_dir is None:
        return (
            "LPIPS not computed: no weights folder given and nothing is downloaded; pass a "
            f"folder holding {expected}"
        )
    folder = Path(weights_dir)
    if not folder.is_dir():
        return (
            f"LPIPS not computed: weights folder {folder} does not exist; it should hold {expected}"
        )
    missing = [f for f in (spec.linear_file, spec.backbone_file) if not (folder / f).is_file()]
    if missing:
        return (
            f"LPIPS not computed: {folder} lacks {' and '.join(missing)}; it should hold {expected}"
        )
    return None


def lpips_available(
    weights_dir: str | os.PathLike | None = None, net: str = "alex"
) -> tuple[bool, str]:
    """Whether LPIPS can be computed from local weights, and why (not).

    Checks that the two files :func:`load_lpips` needs exist in ``weights_dir`` and that
    torchvision imports; it does not read the (large) files, so a corrupt file is only found by
    :func:`load_lpips`, which raises.

    Args:
        weights_dir: the folder holding the weights, or None.
        net: ``"alex"`` (the lpips default) or ``"vgg"``.

    Returns:
        ``(True, description)`` or ``(False, reason)``, the reason naming the folder and the
        missing files.
    """
    spec = _lpips_spec(net)
    reason = _missing_weights_reason(weights_dir, spec)
    if reason is not None:
        return False, reason
    try:
        from nerfmeta.compat import import_torchvision

        import_torchvision()
    except ImportError as exc:
        return False, f"LPIPS not computed: torchvision cannot be imported ({exc})"
    return True, f"LPIPS v0.1 ({spec.name}) from {Path(weights_dir)}"


def _load_state_dict(path: Path) -> dict[str, torch.Tensor]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch.load raises many types for a bad file; re-raised below
        raise LpipsWeightsError(
            f"cannot read LPIPS weights {path}: {exc}; replace it with the original file"
        ) from exc
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise LpipsWeightsError(
            f"{path} is not a state dict of tensors; replace it with the original file"
        )
    return state


class LpipsNetwork(nn.Module):
    """LPIPS v0.1 (Zhang et al. 2018) with frozen, locally loaded weights.

    Build it with :func:`load_lpips`. Reproduces ``lpips.LPIPS(net=..., version="0.1")``:
    scaling layer, backbone features tapped after each ReLU block, unit-normalised along
    channels, squared difference, learned non-negative 1x1 weights, spatial mean, sum of taps.
    """

    def __init__(self, spec: LpipsSpec, features: nn.Sequential, linear: list[torch.Tensor]):
        super().__init__()
        self.spec = spec
        starts = (0,) + spec.slice_ends[:-1]
        self.slices = nn.ModuleList(
            features[a:b] for a, b in zip(starts, spec.slice_ends, strict=True)
        )
        self.linear = nn.ParameterList(nn.Parameter(w, requires_grad=False) for w in linear)
        self.register_buffer("shift", torch.tensor(_LPIPS_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_LPIPS_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        h = (x - self.shift) / self.scale
        taps = []
        for block in self.slices:
            h = block(h)
            norm = torch.sqrt(torch.sum(h * h, dim=1, keepdim=True))
            taps.append(h / (norm + 1e-10))
        return taps

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """LPIPS distance.

        Args:
            x: (N, 3, H, W) images in [-1, 1], channel-first as the backbone expects.
            y: same shape as ``x``.

        Returns:
            (N,) distances, 0 for identical images.
        """
        # Two separate passes (not one batch of 2N) so identical images give identical
        # features bit for bit, whatever algorithm the convolution picks for the batch.
        total = x.new_zeros(x.shape[0])
        for fx, fy, w in zip(self._taps(x), self._taps(y), self.linear, strict=True):
            total = total + F.conv2d((fx - fy) ** 2, w).mean(dim=(1, 2, 3))
        return total


def load_lpips(
    weights_dir: str | os.PathLike | None, net: str = "alex", *, device=None
) -> LpipsNetwork:
    """Build LPIPS v0.1 from weights already on disk (nothing is downloaded).

    ``weights_dir`` must hold two files (see :data:`LPIPS_NETWORKS`):

    - ``alex.pth`` / ``vgg.pth``: the linear-layer weights shipped inside the ``lpips`` pip
      package, ``<site-packages>/lpips/weights/v0.1/alex.pth``; a state dict with keys
      ``lin0.model.1.weight`` ... ``lin4.model.1.weight`` of shape (1, C_k, 1, 1).
    - ``alexnet-owt-7be5be79.pth`` / ``vgg16-397923af.pth``: torchvision's ImageNet state dict
      (``AlexNet_Weights.IMAGENET1K_V1`` / ``VGG16_Weights.IMAGENET1K_V1``) under the name
      torchvision caches it in ``~/.cache/torch/hub/checkpoints/``. Only ``features.*`` is
      used; a file holding just those keys works too.

    Files are read with ``torch.load(weights_only=True)`` and their keys and shapes checked;
    their hashes are not (torchvision checks those when it downloads).

    Args:
        weights_dir: the folder holding both files.
        net: ``"alex"`` (the lpips default) or ``"vgg"``.
        device: where to put the network (default CPU).

    Returns:
        the frozen network in eval mode, float32.

    Raises:
        MetricUnavailable: a file is missing (the message names it and where to get it).
        LpipsWeightsError: a file cannot be read or its keys/shapes do not fit.
    """
    spec = _lpips_spec(net)
    reason = _missing_weights_reason(weights_dir, spec)
    if reason is not None:
        raise MetricUnavailable(reason)
    folder = Path(weights_dir)
    device = torch.device("cpu") if device is None else torch.device(device)
    from nerfmeta.compat import import_torchvision

    tv = import_torchvision()

    backbone_path = folder / spec.backbone_file
    # Read on the CPU: the file also holds the (unused, large) classifier.
    state = _load_state_dict(backbone_path)
    prefix = "features."
    features_state = {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}
    unexpected = sorted(k for k in state if not k.startswith(("features.", "classifier.")))
    # Built on the meta device: no random init, no memory; the loaded tensors are assigned.
    with torch.device("meta"):
        features = getattr(tv.models, spec.builder)(weights=None).features
    if unexpected or set(features_state) != set(features.state_dict()):
        raise LpipsWeightsError(
            f"{backbone_path} is not a torchvision {spec.builder} state dict (expected keys "
            f"features.{{{', '.join(features.state_dict())}}}); replace it with the file of "
            f"{spec.backbone_weights}"
        )
    try:
        features.load_state_dict(features_state, strict=True, assign=True)
    except RuntimeError as exc:
        raise LpipsWeightsError(
            f"{backbone_path} does not fit torchvision {spec.builder}: {exc}"
        ) from exc

    linear_path = folder / spec.linear_file
    state = _load_state_dict(linear_path)
    expected = [f"lin{k}.model.1.weight" for k in range(len(spec.channels))]
    if sorted(state) != sorted(expected):
        raise LpipsWeightsError(
            f"{linear_path} does not hold the LPIPS v0.1 {spec.name} linear layers (expected "
            f"keys {', '.join(expected)}, found {', '.join(sorted(state)) or 'none'}); copy "
            f"lpips/weights/v0.1/{spec.linear_file} from the lpips package"
        )
    linear = []
    for key, c in zip(expected, spec.channels, strict=True):
        if tuple(state[key].shape) != (1, c, 1, 1):
            raise LpipsWeightsError(
                f"{linear_path}: {key} has shape {tuple(state[key].shape)}, expected (1, {c}, 1, 1)"
            )
        linear.append(state[key].float())
    network = LpipsNetwork(spec, features, linear)
    return network.to(device=device, dtype=torch.float32)


def lpips(
    pred: torch.Tensor,
    target: torch.Tensor,
    weights: str | os.PathLike | LpipsNetwork | None,
    *,
    net: str = "alex",
    data_range: float = 1.0,
    per_image: bool = False,
) -> torch.Tensor:
    """LPIPS v0.1 distance (lower is better), from local weights only.

    Args:
        pred: (H, W, 3) or (N, H, W, 3) images in ``[0, data_range]``; at least about 32x32
            for alex.
        target: same shape as ``pred``.
        weights: a network from :func:`load_lpips` (reuse it across calls: building one reads
            the backbone file), or the folder it is loaded from (see :func:`load_lpips`).
        net: which network to load when ``weights`` is a folder.
        data_range: the difference between the largest and smallest possible pixel value.
        per_image: one value per image instead of the mean.

    Returns:
        () or, with ``per_image``, (N,) for a batch and () for one image, in the dtype and on
        the device of ``pred``. Computed in the network's dtype (float32).

    Raises:
        MetricUnavailable: ``weights`` is a folder without the needed files. Never a made-up
            number: check :func:`lpips_available` first to report the reason instead.
    """
    _check_pair(pred, target)
    _check_data_range(data_range)
    if pred.ndim not in (3, 4) or pred.shape[-1] != 3:
        raise ValueError(f"LPIPS needs (H, W, 3) or (N, H, W, 3) images, got {tuple(pred.shape)}")
    if isinstance(weights, LpipsNetwork):
        network = weights
    else:
        network = load_lpips(weights, net, device=pred.device)
    param = network.linear[0]
    if param.device != pred.device:
        raise ValueError(
            f"the LPIPS network is on {param.device} but the images are on {pred.device}; "
            "load it with load_lpips(..., device=images.device)"
        )
    single = pred.ndim == 3

    def to_input(img: torch.Tensor) -> torch.Tensor:
        img = img.unsqueeze(0) if single else img
        img = img.to(param.dtype).permute(0, 3, 1, 2)
        return img * (2.0 / data_range) - 1.0  # [0, data_range] -> [-1, 1]

    per = network(to_input(pred), to_input(target))
    if single:
        per = per[0]
    out = per if per_image else per.mean()
    return out.to(pred.dtype) if pred.dtype.is_floating_point else out


# --------------------------------------------------------------------------------------------
# Evaluation summary
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImageMetrics:
    """Image quality of a set of rendered views, each a mean over the images.

    Attributes:
        psnr: mean over images of the per-image PSNR in dB (``inf`` if an image is exact).
        ssim: mean over images of the per-image SSIM (:func:`ssim`).
        lpips: mean over images of LPIPS v0.1, or None when it could not be computed.
        lpips_note: why ``lpips`` is None, or which network and weights computed it.
    """

    psnr: float
    ssim: float
    lpips: float | None
    lpips_note: str | None


def evaluate_images(
    pred: torch.Tensor,
    target: torch.Tensor,
    lpips_weights: str | os.PathLike | LpipsNetwork | None = None,
    *,
    lpips_net: str = "alex",
) -> ImageMetrics:
    """PSNR, SSIM and (when its weights are on disk) LPIPS of rendered views.

    A missing LPIPS weights folder or file is reported in ``lpips_note`` with ``lpips=None``; a
    file that is present but broken raises :class:`LpipsWeightsError`.

    Args:
        pred: (N, H, W, 3) rendered images in [0, 1].
        target: (N, H, W, 3) ground-truth images in [0, 1].
        lpips_weights: a folder for :func:`load_lpips`, a loaded :class:`LpipsNetwork`, or
            None to skip LPIPS.
        lpips_net: which LPIPS network to load from a folder.

    Returns:
        the metrics, each the mean over the N images.
    """
    _check_pair(pred, target)
    if pred.ndim != 4 or pred.shape[-1] != 3 or pred.shape[0] == 0:
        raise ValueError(
            f"evaluate_images needs (N, H, W, 3) images with N >= 1, got {tuple(pred.shape)}"
        )
    if isinstance(lpips_weights, LpipsNetwork):
        network, note = lpips_weights, f"LPIPS v0.1 ({lpips_weights.spec.name})"
    else:
        ok, note = lpips_available(lpips_weights, lpips_net)
        network = load_lpips(lpips_weights, lpips_net, device=pred.device) if ok else None
    with torch.no_grad():
        psnr_value = psnr(pred, target, per_image=True).mean().item()
        # One image at a time: SSIM and LPIPS hold several full-size maps per image.
        ssim_value = sum(ssim(p, t).item() for p, t in zip(pred, target)) / pred.shape[0]
        lpips_value = None
        if network is not None:
            total = sum(lpips(p, t, network).item() for p, t in zip(pred, target))
            lpips_value = total / pred.shape[0]
    return ImageMetrics(psnr=psnr_value, ssim=ssim_value, lpips=lpips_value, lpips_note=note)
