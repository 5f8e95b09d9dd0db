"""The five input encodings: shapes, exact values, hash indices, gradients, and the NeRF MLP using each."""

import math

import pytest
import torch

from nerfmeta.errors import ConfigError
from nerfmeta.fields.encodings import (
    ENCODINGS,
    EncodingChoice,
    FourierConfig,
    FourierFeatures,
    HashGrid,
    HashGridConfig,
    PEConfig,
    PositionalEncoding,
    build_encoding,
    corner_index,
    encoding_config,
    interpolate_level,
    level_resolutions,
)
from nerfmeta.fields.nerf_mlp import NerfMLP, NerfMLPConfig

SMALL = EncodingChoice(fourier_features=8, hash_levels=3, hash_features=2, hash_log2_size=8, hash_base_res=2,
                       hash_finest_res=16, nffb_width=4)


def small(name: str) -> torch.nn.Module:
    return build_encoding(encoding_config(EncodingChoice(**{**SMALL.__dict__, "encoding": name}), 2))


@pytest.mark.parametrize("name", ENCODINGS)
def test_shapes_input_columns_and_gradients(name):
    enc = small(name)
    x = (torch.rand(2, 5, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1).requires_grad_(True)
    y = enc(x)
    assert y.shape == (2, 5, enc.out_dim)
    assert torch.equal(y[..., :3], x)  # every encoding keeps x first (geometric init relies on it)
    y.square().sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    for p in enc.parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


@pytest.mark.parametrize("name", ENCODINGS)
def test_every_encoding_takes_no_points(name):
    """A batch can leave no sample to encode (an SDF fit whose rays all miss the marched band did, with the hash grid:
    'cannot reshape tensor of 0 elements'); every encoding and the SDF built on it must give empty results."""
    from nerfmeta.fields.sdf import SdfConfig, SdfField

    enc = small(name)
    x = torch.zeros(0, 3, requires_grad=True)
    y = enc(x)
    assert y.shape == (0, enc.out_dim)
    y.sum().backward()
    field = SdfField(SdfConfig(**{**SMALL.__dict__, "encoding": name}, depth=2, width=16, feature_dim=4),
                     torch.tensor([[-1.0] * 3, [1.0] * 3]))
    out = field.evaluate(torch.zeros(0, 3))
    assert out.sdf.shape == (0,) and out.grad.shape == (0, 3)


def test_pe_values_at_known_points():
    enc = PositionalEncoding(PEConfig(2))
    y = enc(torch.tensor([[0.5, 0.0, -0.25]]))[0]
    # columns: x (3), sin(pi x), sin(2 pi x) (k-major, 3 each), then the cosines
    expect = [0.5, 0.0, -0.25,
              1.0, 0.0, -math.sqrt(0.5), 0.0, 0.0, -1.0,
              0.0, 1.0, math.sqrt(0.5), -1.0, 1.0, 0.0]
    assert torch.allclose(y, torch.tensor(expect), atol=1e-6)


def test_fourier_sigma_respected_and_seeded():
    a = FourierFeatures(FourierConfig(n_features=4000, sigma=7.0, seed=3))
    assert abs(float(a.b.std()) - 7.0) < 0.15
    b = FourierFeatures(FourierConfig(n_features=4000, sigma=7.0, seed=3))
    assert torch.equal(a.b, b.b)
    x = torch.tensor([[0.1, 0.2, 0.3]])
    proj = 2 * math.pi * (x @ a.b.t())
    assert torch.allclose(a(x)[0, 3:4003], torch.sin(proj)[0], atol=1e-5)


def test_level_resolutions_geometric():
    assert level_resolutions(5, 16, 256) == [16, 32, 64, 128, 256]
    assert level_resolutions(1, 8, 8) == [8]


def test_hash_indices_deterministic_and_in_range():
    ijk = torch.randint(0, 513, (1000, 3), generator=torch.Generator().manual_seed(0))
    idx = corner_index(ijk, 512, 2**10)
    assert torch.equal(idx, corner_index(ijk, 512, 2**10))
    assert int(idx.min()) >= 0 and int(idx.max()) < 2**10
    # exact hash of one corner: (1 * 1) xor (2 * 2654435761) xor (3 * 805459861), mod 2^10
    assert int(corner_index(torch.tensor([1, 2, 3]), 512, 2**10)) == (1 ^ (2 * 2654435761) ^ (3 * 805459861)) % 1024
    # a level that fits the table indexes corners one to one
    dense = corner_index(torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [4, 4, 4]]), 4, 2**10)
    assert dense.tolist() == [0, 1, 5, 25, 124]


def test_trilinear_interpolation_is_exact_for_linear_tables():
    res = 4
    side = res + 1
    ijk = torch.stack(torch.meshgrid(*[torch.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    table = torch.zeros(side**3, 1)
    table[corner_index(ijk, res, side**3), 0] = (ijk.float() @ torch.tensor([1.0, -2.0, 0.5]))
    x = torch.rand(50, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    pos = (x + 1) * 0.5 * res
    assert torch.allclose(interpolate_level(table, x, res)[:, 0], pos @ torch.tensor([1.0, -2.0, 0.5]), atol=1e-5)


def test_tiny_hash_table_stays_finite():
    enc = HashGrid(HashGridConfig(levels=4, features=2, log2_size=2, base_res=4, finest_res=64))
    y = enc(torch.rand(100, 3) * 2 - 1)
    assert y.shape == (100, 3 + 8) and torch.isfinite(y).all()


def test_unknown_encoding_is_refused():
    with pytest.raises(ConfigError, match="encoding='bogus'"):
        NerfMLP(NerfMLPConfig(encoding="bogus"), torch.tensor([[-1.0] * 3, [1.0] * 3]))


@pytest.mark.parametrize("name", ENCODINGS)
def test_nerf_mlp_renders_with_every_encoding(name):
    from nerfmeta.data.scene import RayBatch
    from nerfmeta.fields.base import check_partition

    cfg = NerfMLPConfig(**{**SMALL.__dict__, "encoding": name}, pos_freqs=2, depth=2, width=16, skips=(), n_samples=8)
    model = NerfMLP(cfg, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    check_partition(model)
    rays = RayBatch(origins=torch.tensor([[0.0, 0.0, -3.0]] * 4), directions=torch.tensor([[0.0, 0.0, 1.0]] * 4),
                    near=torch.full((4,), 2.0), far=torch.full((4,), 4.0))
    out = model(rays, background=torch.ones(3), train=True, generator=torch.Generator().manual_seed(0),
                target=torch.zeros(4, 3))
    out.losses["mse"].backward()
    assert all(p.grad is not None for p in model.parameters())
    if name in ("hash", "nffb", "stylemod-nffb"):  # learnable encodings get their own rate
        assert [g.name for g in model.param_groups()] == ["mlp", "encoding"]
