"""Input encodings as small modules, selectable by name: ``pe``, ``fourier``, ``hash``, ``nffb``, ``stylemod-nffb``.

Every encoding maps box-normalised points ``x`` (..., 3) in [-1, 1]^3 to features (..., out_dim)
whose first three columns are ``x`` itself (``include_input``: an SDF's geometric initialisation
zeroes the first layer's weights on every other column, so any encoding starts as a sphere).

- ``pe``: NeRF's positional encoding, ``sin/cos(2^k pi x)`` (Mildenhall et al., ECCV 2020).
- ``fourier``: random Fourier features ``sin/cos(2 pi B x)``, ``B ~ N(0, sigma^2)`` (Tancik et al.,
  "Fourier Features Let Networks Learn High Frequency Functions in Low Dimensional Domains",
  NeurIPS 2020); ``B`` is drawn from a seeded generator and kept as a buffer.
- ``hash``: instant-ngp's multi-resolution hash grid (Mueller et al., "Instant Neural Graphics
  Primitives with a Multiresolution Hash Encoding", SIGGRAPH 2022) in pure PyTorch: ``levels``
  grids with resolutions growing geometrically from ``base_res`` to ``finest_res``, each corner's
  ``features`` looked up directly when the level fits in the table, else through the spatial hash
  ``(i * 1) xor (j * 2654435761) xor (k * 805459861) mod 2^log2_size``; trilinear interpolation.
- ``nffb``: neural Fourier filter banks (Wu, Jin and Yi, "Neural Fourier Filter Bank", CVPR 2023):
  the space is split by multi-resolution grids and by frequency: level ``l``'s grid features pass
  through a Fourier feature map of band ``sigma_l`` (growing geometrically with the grid's
  resolution, a coarse grid with low frequencies), and a sine network accumulates the levels,
  higher bands on top of lower ones: ``h_l = sin(W_l h_{l-1} + b_l) + sin(2 pi sigma_l B_l g_l(x))``,
  ``h_0`` a Fourier map of ``x`` at the lowest band. The output is ``[x, h_1, ..., h_L]``.
- ``stylemod-nffb``: NFFB whose levels also *modulate* the sine layers, as StyleGAN's style
  modulation scales a layer per channel: ``h_l = sin(s_l * (W_l h_{l-1}) + b_l) + f_l`` with
  ``f_l`` level ``l``'s filtered grid features and the style ``s_l = 1 + A_l f_l`` (``A_l``
  starting at zero, so it starts as ``nffb``). This is our reading of the source study's variant.

Grid encodings (``hash``, ``nffb``, ``stylemod-nffb``) are piecewise trilinear: their gradient in
``x`` jumps at cell faces, so an SDF takes numerical gradients through them (as Neuralangelo does).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from nerfmeta.errors import ConfigError
from nerfmeta.fields.encoding import encoding_dim, positional_encoding

ENCODINGS = ("pe", "fourier", "hash", "nffb", "stylemod-nffb")
GRID_ENCODINGS = ("hash", "nffb", "stylemod-nffb")
HASH_PRIMES = (1, 2654435761, 805459861)
"""instant-ngp's per-axis primes of the spatial hash."""


@dataclass(frozen=True)
class PEConfig:
    """Settings of :class:`PositionalEncoding`."""

    n_freqs: int = 6
    """Octaves ``k = 0 .. n_freqs - 1`` of ``sin/cos(2^k pi x)``."""


@dataclass(frozen=True)
class FourierConfig:
    """Settings of :class:`FourierFeatures`."""

    n_features: int = 64
    """Rows of the random frequency matrix ``B`` (the output has ``2 n_features + 3`` columns)."""
    sigma: float = 4.0
    """Standard deviation of ``B``'s entries, in cycles per unit of the [-1, 1] box."""
    seed: int = 0
    """Seed of the generator ``B`` is drawn from."""


@dataclass(frozen=True)
class HashGridConfig:
    """Settings of :class:`HashGrid` (instant-ngp's notation: L, F, log2 T, N_min, N_max)."""

    levels: int = 8
    """Number of grid levels L."""
    features: int = 2
    """Features per corner F."""
    log2_size: int = 15
    """log2 of the table size T per level."""
    base_res: int = 8
    """Coarsest resolution N_min (cells per axis)."""
    finest_res: int = 128
    """Finest resolution N_max (cells per axis)."""
    init_scale: float = 1e-4
    """Table entries start uniform in [-init_scale, init_scale] (instant-ngp: 1e-4)."""
    seed: int = 0
    """Seed of the table initialisation."""


@dataclass(frozen=True)
class NFFBConfig:
    """Settings of :class:`NFFB` (and of its StyleMod variant)."""

    grid: HashGridConfig = HashGridConfig(levels=6, features=2, log2_size=15, base_res=4, finest_res=128, init_scale=0.1)
    """The multi-resolution grids, one per filter-bank level."""
    width: int = 16
    """Width of each level's sine layer."""
    sigma_min: float = 1.0
    """Frequency band of the coarsest level (and of the input map ``h_0``)."""
    sigma_max: float = 32.0
    """Frequency band of the finest level."""
    stylemod: bool = False
    """Modulate each level's sine layer by its filtered grid features (StyleMod-NFFB)."""
    seed: int = 0
    """Seed of the random frequency matrices and the sine layers' initialisation."""


class PositionalEncoding(nn.Module):
    """NeRF's positional encoding (Mildenhall et al. 2020): ``[x, sin(2^k pi x), cos(2^k pi x)]``."""

    uses_grid = False

    def __init__(self, config: PEConfig):
        super().__init__()
        self.config = config
        self.out_dim = encoding_dim(3, config.n_freqs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., 3) in [-1, 1] -> (..., 3 + 6 n_freqs)."""
        return positional_encoding(x, self.config.n_freqs)


def fourier_features(x: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``[x, sin(2 pi x B^T), cos(2 pi x B^T)]`` of points (..., D) with a frequency matrix ``b`` (m, D): (..., D + 2m)."""
    proj = 2.0 * math.pi * (x @ b.t())
    return torch.cat([x, torch.sin(proj), torch.cos(proj)], dim=-1)


class FourierFeatures(nn.Module):
    """Random Fourier features (Tancik et al. 2020) with ``B ~ N(0, sigma^2)`` from a seeded generator (a buffer)."""

    uses_grid = False

    def __init__(self, config: FourierConfig):
        super().__init__()
        self.config = config
        gen = torch.Generator().manual_seed(config.seed)
        self.register_buffer("b", config.sigma * torch.randn(config.n_features, 3, generator=gen))
        self.out_dim = 3 + 2 * config.n_features

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., 3) in [-1, 1] -> (..., 3 + 2 n_features)."""
        return fourier_features(x, self.b.to(x.dtype))


def level_resolutions(levels: int, base_res: int, finest_res: int) -> list[int]:
    """instant-ngp's per-level resolutions ``floor(N_min * b^l)``, ``b = exp((ln N_max - ln N_min) / (L - 1))``."""
    if levels == 1:
        return [base_res]
    growth = math.exp((math.log(finest_res) - math.log(base_res)) / (levels - 1))
    return [int(math.floor(base_res * growth**level + 1e-6)) for level in range(levels)]


def corner_index(ijk: torch.Tensor, res: int, table_size: int) -> torch.Tensor:
    """(...) int64 table row of integer grid corners ``ijk`` (..., 3) in ``0 .. res`` of one level.

    A level whose ``(res + 1)^3`` corners fit in the table indexes them one to one
    (``i + j (res + 1) + k (res + 1)^2``); a finer one hashes them (instant-ngp's xor of primes),
    wrapped to ``table_size`` (a power of two).
    """
    side = res + 1
    if side**3 <= table_size:
        return ijk[..., 0] + side * (ijk[..., 1] + side * ijk[..., 2])
    h = ijk[..., 0] * HASH_PRIMES[0]
    h = torch.bitwise_xor(h, ijk[..., 1] * HASH_PRIMES[1])
    h = torch.bitwise_xor(h, ijk[..., 2] * HASH_PRIMES[2])
    return torch.bitwise_and(h, table_size - 1)


def interpolate_level(table: torch.Tensor, x: torch.Tensor, res: int) -> torch.Tensor:
    """Trilinear interpolation of one level's corner features.

    Args:
        table: (T, F) the level's feature table.
        x: (N, 3) points in [-1, 1] (clamped to it).
        res: cells per axis of the level.

    Returns:
        (N, F) features.
    """
    pos = ((x.clamp(-1.0, 1.0) + 1.0) * (0.5 * res))
    base = torch.floor(pos).clamp(max=res - 1)
    frac = pos - base  # (N, 3): gradient in x flows through here
    offsets = torch.tensor([[(corner >> a) & 1 for a in range(3)] for corner in range(8)], device=x.device)  # (8, 3)
    idx = corner_index(base.long()[None] + offsets[:, None], res, table.shape[0])  # (8, N)
    w = torch.where(offsets[:, None].bool(), frac[None], 1.0 - frac[None]).prod(-1)  # (8, N)
    feats = table.index_select(0, idx.reshape(-1)).view(8, x.shape[0], table.shape[1]).to(x.dtype)  # N may be 0
    return (w[..., None] * feats).sum(0)


class HashGrid(nn.Module):
    """instant-ngp's multi-resolution hash encoding (Mueller et al. 2022), pure PyTorch, trilinear.

    Parameters: ``tables`` (L, T_l, F) with ``T_l = min(2^log2_size, (N_l + 1)^3)`` stacked to
    the largest, so a coarse level uses only its first rows.
    """

    uses_grid = True

    def __init__(self, config: HashGridConfig):
        super().__init__()
        if config.levels < 1 or config.features < 1 or not 1 <= config.base_res <= config.finest_res or config.log2_size < 1:
            raise ConfigError(f"hash grid {config}: need levels, features >= 1, log2_size >= 1 and 1 <= base_res <= finest_res")
        self.config = config
        self.resolutions = level_resolutions(config.levels, config.base_res, config.finest_res)
        size = max(min(2**config.log2_size, (r + 1) ** 3) for r in self.resolutions)
        gen = torch.Generator().manual_seed(config.seed)
        u = torch.rand(config.levels, size, config.features, generator=gen)
        self.tables = nn.Parameter((2.0 * u - 1.0) * config.init_scale)
        self.out_dim = 3 + config.levels * config.features

    def level_features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Per-level features, L tensors (N, F), of points (N, 3) in [-1, 1]."""
        size = 2**self.config.log2_size
        return [interpolate_level(self.tables[level, : min(size, (res + 1) ** 3)], x, res)
                for level, res in enumerate(self.resolutions)]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., 3) in [-1, 1] -> (..., 3 + levels * features)."""
        flat = x.reshape(-1, 3)
        feats = torch.cat([flat, *self.level_features(flat)], dim=-1)
        return feats.reshape(*x.shape[:-1], self.out_dim)


class NFFB(nn.Module):
    """Neural Fourier filter bank (Wu, Jin and Yi, CVPR 2023) as an encoding; StyleMod variant with ``stylemod``.

    See the module docstring for the equations. Parameters: the grids' ``tables``, the sine
    layers ``layers.l`` (width x width, SIREN's uniform init) and, with ``stylemod``, the
    zero-initialised style maps ``styles.l``; buffers ``b_in`` (width, 3) and ``b`` (L, width, F),
    the random frequency matrices of unit variance (scaled by each level's band on use).
    """

    uses_grid = True

    def __init__(self, config: NFFBConfig):
        super().__init__()
        if config.width < 1 or not 0.0 < config.sigma_min <= config.sigma_max:
            raise ConfigError(f"nffb {config}: need width >= 1 and 0 < sigma_min <= sigma_max")
        self.config = config
        self.grid = HashGrid(config.grid)
        levels, w = config.grid.levels, config.width
        self.sigmas = [float(s) for s in torch.logspace(math.log10(config.sigma_min), math.log10(config.sigma_max), levels)]
        gen = torch.Generator().manual_seed(config.seed)
        self.register_buffer("b_in", torch.randn(w, 3, generator=gen))
        self.register_buffer("b", torch.randn(levels, w, config.grid.features, generator=gen))
        bound = math.sqrt(6.0 / w)
        self.layers = nn.ModuleList(nn.Linear(w, w) for _ in range(levels))
        with torch.no_grad():
            for layer in self.layers:
                layer.weight.copy_((2.0 * torch.rand(w, w, generator=gen) - 1.0) * bound)
                layer.bias.zero_()
        if config.stylemod:
            self.styles = nn.ModuleList(nn.Linear(w, w) for _ in range(levels))
            for style in self.styles:
                nn.init.zeros_(style.weight)
                nn.init.zeros_(style.bias)
        self.out_dim = 3 + levels * w

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., 3) in [-1, 1] -> (..., 3 + levels * width)."""
        flat = x.reshape(-1, 3)
        h = torch.sin(2.0 * math.pi * self.config.sigma_min * (flat @ self.b_in.to(flat.dtype).t()))
        outs = [flat]
        for level, g in enumerate(self.grid.level_features(flat)):
            filtered = torch.sin(2.0 * math.pi * self.sigmas[level] * (g @ self.b[level].to(g.dtype).t()))  # (N, width)
            pre = nn.functional.linear(h, self.layers[level].weight, None)
            if self.config.stylemod:
                pre = (1.0 + self.styles[level](filtered)) * pre
            h = torch.sin(pre + self.layers[level].bias) + filtered
            outs.append(h)
        return torch.cat(outs, dim=-1).reshape(*x.shape[:-1], self.out_dim)


@dataclass(frozen=True)
class EncodingChoice:
    """Which input encoding a field uses, with each encoding's main settings (a backbone config inherits these)."""

    encoding: str = "pe"
    """Input encoding of positions: pe, fourier, hash, nffb or stylemod-nffb."""
    fourier_features: int = 64
    """fourier: rows of the random frequency matrix B."""
    fourier_sigma: float = 4.0
    """fourier: standard deviation of B's entries (cycles per unit of the [-1, 1] box)."""
    hash_levels: int = 8
    """hash, nffb: number of grid levels."""
    hash_features: int = 2
    """hash, nffb: features per grid corner."""
    hash_log2_size: int = 15
    """hash, nffb: log2 of each level's table size."""
    hash_base_res: int = 8
    """hash, nffb: coarsest grid resolution (cells per axis)."""
    hash_finest_res: int = 128
    """hash, nffb: finest grid resolution (cells per axis)."""
    nffb_width: int = 16
    """nffb: width of each level's sine layer."""
    nffb_sigma_max: float = 32.0
    """nffb: frequency band of the finest level (the coarsest has 1)."""
    encoding_seed: int = 0
    """Seed of the encoding's random matrices and tables."""
    encoding_lr: float = 1e-2
    """Adam learning rate of the encoding's own parameters (hash tables, NFFB layers)."""


def encoding_config(choice: EncodingChoice, pe_freqs: int) -> PEConfig | FourierConfig | HashGridConfig | NFFBConfig:
    """The config of the encoding ``choice.encoding`` names (``pe_freqs``: the backbone's PE octaves)."""
    grid = HashGridConfig(levels=choice.hash_levels, features=choice.hash_features, log2_size=choice.hash_log2_size,
                          base_res=choice.hash_base_res, finest_res=choice.hash_finest_res, seed=choice.encoding_seed)
    if choice.encoding == "pe":
        return PEConfig(pe_freqs)
    if choice.encoding == "fourier":
        return FourierConfig(choice.fourier_features, choice.fourier_sigma, choice.encoding_seed)
    if choice.encoding == "hash":
        return grid
    if choice.encoding in ("nffb", "stylemod-nffb"):
        return NFFBConfig(grid=HashGridConfig(**{**grid.__dict__, "init_scale": 0.1}), width=choice.nffb_width,
                          sigma_max=choice.nffb_sigma_max, stylemod=choice.encoding == "stylemod-nffb",
                          seed=choice.encoding_seed)
    raise ConfigError(f"encoding={choice.encoding!r} is not known: use one of {', '.join(ENCODINGS)}")


def build_encoding(config: PEConfig | FourierConfig | HashGridConfig | NFFBConfig) -> nn.Module:
    """The encoding module of a config (each has ``out_dim`` and ``uses_grid``)."""
    kinds = {PEConfig: PositionalEncoding, FourierConfig: FourierFeatures, HashGridConfig: HashGrid, NFFBConfig: NFFB}
    return kinds[type(config)](config)
