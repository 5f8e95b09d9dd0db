"""NeRF MLP backbone: layer partition and order, the initial-alpha shift and a constant field by hand,
rendering properties, fitting, freezing, importance sampling, functional and second-order calls."""

import dataclasses
import json
import math

import pytest
import torch
from torch.func import functional_call

from nerfmeta.data.scene import RayBatch
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import check_partition
from nerfmeta.fields.nerf_mlp import NERF_PAPER, NERF_SMALL, PRESETS, NerfMLP, NerfMLPConfig

TINY = NerfMLPConfig(pos_freqs=3, dir_freqs=2, depth=3, width=16, skips=(2,), n_samples=12)
BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
WHITE = torch.ones(3)


def _model(config=TINY, bounds=BOX, seed=0):
    return NerfMLP(config, bounds, generator=torch.Generator().manual_seed(seed))


def _rays(n=32, seed=0, near=2.0, far=6.0, dtype=torch.float32):
    """Rays from a sphere of radius 4 towards random points near the origin."""
    g = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=dtype), dim=-1) * 4.0
    aim = 0.5 * torch.randn(n, 3, generator=g, dtype=dtype)
    directions = torch.nn.functional.normalize(aim - origins, dim=-1)
    target = torch.rand(n, 3, generator=g, dtype=dtype)
    full = torch.full((n,), 1.0, dtype=dtype)
    return RayBatch(origins, directions, near * full, far * full, target)


def _set_constant_field(model, density_bias, colour):
    """Make raw density ``density_bias`` and colour ``colour`` everywhere."""
    with torch.no_grad():
        model.density.weight.zero_()
        model.density.bias.fill_(density_bias)
        model.rgb.weight.zero_()
        model.rgb.bias.copy_(torch.logit(torch.as_tensor(colour, dtype=model.rgb.bias.dtype)))


# -- interface -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "config",
    [
        TINY,
        dataclasses.replace(TINY, view_dependent=False),
        dataclasses.replace(TINY, skips=(), pos_freqs=0, dir_freqs=0),
        dataclasses.replace(TINY, skips=(1, 2), n_importance=8),
        NERF_SMALL,
        NERF_PAPER,
    ],
)
def test_layers_and_param_groups_partition_the_parameters(config):
    model = _model(config)
    check_partition(model)
    view = ["feature", "view.0"] if config.view_dependent else []
    expected = [f"trunk.{i}" for i in range(config.depth)] + ["density"] + view + ["rgb"]
    assert [layer.name for layer in model.layers()] == expected
    assert all(layer.param_names == (f"{layer.name}.weight", f"{layer.name}.bias") for layer in model.layers())
    (group,) = model.param_groups()
    assert (group.name, group.lr) == ("mlp", config.lr)


def test_presets():
    assert PRESETS == {"paper": NERF_PAPER, "small": NERF_SMALL}
    assert len(_model(NERF_PAPER).layers()) == 12 and len(_model(NERF_SMALL).layers()) == 8
    # the paper's input widths: 63 for the position, 27 for the direction, skip adds 63
    paper = _model(NERF_PAPER)
    assert paper.trunk[0].in_features == 63 and paper.trunk[4].in_features == 256 + 63
    assert paper.view[0].in_features == 256 + 27 and paper.view[0].out_features == 128


@pytest.mark.parametrize("view_dependent", [True, False])
def test_layers_are_listed_in_forward_order(view_dependent):
    model = _model(dataclasses.replace(TINY, view_dependent=view_dependent))
    calls = []
    names = {module: name for name, module in model.named_modules()}
    handles = [
        m.register_forward_hook(lambda mod, args, out: calls.append(names[mod]))
        for m in model.modules()
        if isinstance(m, torch.nn.Linear)
    ]
    model(_rays(4), background=WHITE)
    for h in handles:
        h.remove()
    assert calls == [layer.name for layer in model.layers()]


def test_without_view_branch_colour_ignores_the_direction():
    points = torch.randn(5, 7, 3)
    d1 = torch.nn.functional.normalize(torch.randn(5, 1, 3), dim=-1)
    d2 = torch.nn.functional.normalize(torch.randn(5, 7, 3), dim=-1)
    flat = _model(dataclasses.replace(TINY, view_dependent=False))
    assert not any("view" in n or "feature" in n for n, _ in flat.named_parameters())
    sigma1, rgb1 = flat.query(points, d1)
    sigma2, rgb2 = flat.query(points, d2)
    sigma3, rgb3 = flat.query(points)
    assert sigma1.shape == (5, 7) and rgb1.shape == (5, 7, 3)
    assert torch.equal(rgb1, rgb2) and torch.equal(rgb1, rgb3)
    assert torch.equal(sigma1, sigma2) and torch.equal(sigma1, sigma3)
    # the view-dependent model does see the direction, but its density does not
    model = _model(TINY)
    sigma1, rgb1 = model.query(points, d1)
    sigma2, rgb2 = model.query(points, d2)
    assert torch.equal(sigma1, sigma2) and not torch.allclose(rgb1, rgb2)
    with pytest.raises(ValueError, match="directions"):
        model.query(points)


# -- numerics by hand ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bounds, far",
    [
        ([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], 2.0),  # box unit 1: 2 world units = 2 box units
        ([[-3.0, -3.0, -3.0], [3.0, 3.0, 3.0]], 6.0),  # box unit 3: scale-free
        ([[-1.0, -2.0, -3.0], [1.0, 2.0, 3.0]], 4.0),  # box unit = mean half-side = 2
    ],
)
@pytest.mark.parametrize("n_samples", [8, 64])
def test_zero_raw_density_gives_alpha_init_per_sample(bounds, far, n_samples):
    config = dataclasses.replace(TINY, n_samples=n_samples, alpha_init=1e-2)
    model = _model(config, torch.tensor(bounds, dtype=torch.float64))
    with torch.no_grad():
        model.density.weight.zero_()
        model.density.bias.zero_()
    # rays of length 2 box units: every sample spans 2 / n_samples box units
    rays = _rays(3, dtype=torch.float64, near=0.0, far=far)
    out = model(rays, background=WHITE.double())
    i = torch.arange(n_samples, dtype=torch.float64)
    expected = 1e-2 * (1 - 1e-2) ** i
    torch.testing.assert_close(out.extras["weights"], expected.expand(3, -1), rtol=1e-12, atol=0)
    torch.testing.assert_close(out.acc, torch.full((3,), 1 - 0.99**n_samples, dtype=torch.float64), rtol=1e-12, atol=0)
    assert math.log1p(math.exp(config.density_shift)) * 2 / n_samples == pytest.approx(-math.log1p(-1e-2), rel=1e-12)
    assert dataclasses.replace(config, density_activation="relu").density_shift == 0.0


@pytest.mark.parametrize("n_importance", [0, 5])
@pytest.mark.parametrize("train", [False, True])
def test_constant_field_renders_in_closed_form(n_importance, train):
    # constant sigma: acc = 1 - exp(-sigma * length in box units) for any sample placement
    bounds = torch.tensor([[-1.0, -2.0, -3.0], [1.0, 2.0, 3.0]], dtype=torch.float64)  # box unit 2
    model = _model(dataclasses.replace(TINY, n_importance=n_importance), bounds)
    _set_constant_field(model, 0.3, [0.25, 0.5, 0.75])
    rays = _rays(6, dtype=torch.float64, near=1.0, far=4.0)
    bg = torch.tensor([0.1, 0.2, 0.9], dtype=torch.float64)
    out = model(rays, background=bg, train=train, generator=torch.Generator().manual_seed(3))
    sigma = torch.nn.functional.softplus(torch.tensor(0.3 + model.config.density_shift, dtype=torch.float64))
    acc = 1 - torch.exp(-sigma * 3.0 / 2.0)
    torch.testing.assert_close(out.acc, acc.expand(6), rtol=1e-12, atol=0)
    rgb = acc * torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64) + (1 - acc) * bg
    torch.testing.assert_close(out.rgb, rgb.expand(6, 3), rtol=1e-12, atol=1e-15)
    # each sample stands for a cell [lo, hi]: the stratified bins, or with importance samples the
    # cells between midpoints of neighbours; its weight is exp(-sigma lo) - exp(-sigma hi)
    t = out.extras["t"]
    if n_importance == 0:
        cuts = 1.0 + 3.0 * torch.arange(1, TINY.n_samples, dtype=torch.float64) / TINY.n_samples
        cuts = cuts.expand(6, -1)
    else:
        cuts = 0.5 * (t[:, 1:] + t[:, :-1])
    lo = torch.cat([torch.full((6, 1), 1.0, dtype=torch.float64), cuts], -1) - 1.0
    hi = torch.cat([cuts, torch.full((6, 1), 4.0, dtype=torch.float64)], -1) - 1.0
    weights = torch.exp(-sigma * lo / 2.0) - torch.exp(-sigma * hi / 2.0)
    torch.testing.assert_close(out.extras["weights"], weights, rtol=1e-10, atol=1e-15)


# -- rendering properties --------------------------------------------------------------------


@pytest.mark.parametrize("n_importance", [0, 6])
def test_shapes_and_ranges(n_importance):
    model = _model(dataclasses.replace(TINY, n_importance=n_importance))
    rays = _rays(40)
    out = model(rays, background=WHITE, train=True, generator=torch.Generator().manual_seed(1))
    assert out.rgb.shape == (40, 3) and out.acc.shape == (40,) and out.depth.shape == (40,)
    assert ((out.rgb >= 0) & (out.rgb <= 1)).all()
    assert ((out.acc >= 0) & (out.acc <= 1)).all()
    assert ((out.depth >= 2.0 - 1e-5) & (out.depth <= 6.0 + 1e-5)).all()
    # nearly opaque rays stop in the first bin, (near, near + bin width)
    _set_constant_field(model, 40.0, [0.5, 0.5, 0.5])
    out = model(rays, background=WHITE)
    assert (out.acc > 1 - 1e-6).all()
    assert ((out.depth > 2.0) & (out.depth < 2.0 + 4.0 / TINY.n_samples)).all()


@pytest.mark.parametrize("n_importance", [0, 4])
@pytest.mark.parametrize("train", [False, True])
def test_zero_length_rays_render_exactly_the_background(n_importance, train):
    model = _model(dataclasses.replace(TINY, n_importance=n_importance, raw_noise_std=1.0))
    rays = _rays(8)
    far = torch.where(torch.arange(8) % 2 == 0, rays.near, rays.far)  # even rays have near == far
    rays = RayBatch(rays.origins, rays.directions, rays.near, far, rays.target)
    bg = torch.rand(8, 3, generator=torch.Generator().manual_seed(0))  # per-ray background
    out = model(rays, background=bg, train=train, generator=torch.Generator().manual_seed(2))
    assert torch.equal(out.rgb[::2], bg[::2])
    assert torch.equal(out.acc[::2], torch.zeros(4))
    assert torch.equal(out.depth[::2], rays.far[::2])
    ((out.rgb - rays.target) ** 2).mean().backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


def test_train_jitters_with_the_generator_and_eval_uses_midpoints():
    rays = _rays(8)

    def render(model, seed, train):
        return model(rays, background=WHITE, train=train, generator=torch.Generator().manual_seed(seed))

    model = _model()
    t = render(model, 0, True).extras["t"]
    assert torch.equal(t, render(model, 0, True).extras["t"])
    assert not torch.equal(t, render(model, 1, True).extras["t"])
    midpoints = 2.0 + 4.0 * (torch.arange(12) + 0.5) / 12
    torch.testing.assert_close(render(model, 0, False).extras["t"], midpoints.expand(8, -1))
    # raw density noise: training only (same seed, so the same weights and the same jitter)
    noisy = _model(dataclasses.replace(TINY, raw_noise_std=0.5))
    assert torch.equal(render(noisy, 0, False).rgb, render(model, 0, False).rgb)
    assert not torch.allclose(render(noisy, 0, True).rgb, render(model, 0, True).rgb)


def test_fitting_a_box_in_front_of_a_background_lowers_the_error():
    config = NerfMLPConfig(pos_freqs=4, dir_freqs=2, depth=3, width=64, skips=(2,), n_samples=16)
    model = _model(config, seed=0)
    # a 16x16 orthographic view down -z: a red square (the box's middle) on a blue background
    s = torch.linspace(-0.9375, 0.9375, 16)
    y, x = torch.meshgrid(s, s, indexing="ij")
    inside = ((x.abs() < 0.5) & (y.abs() < 0.5)).flatten()
    bg = torch.tensor([0.2, 0.4, 0.8])
    target = torch.where(inside[:, None], torch.tensor([0.9, 0.1, 0.1]), bg)
    origins = torch.stack([x.flatten(), y.flatten(), torch.full((256,), 3.0)], -1)
    rays = RayBatch(origins, torch.tensor([0.0, 0.0, -1.0]).expand(256, 3), torch.full((256,), 2.0),
                    torch.full((256,), 4.0), target)
    g = torch.Generator().manual_seed(0)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    with torch.no_grad():
        before = ((model(rays, background=bg).rgb - target) ** 2).mean().item()
    for _ in range(100):
        loss = ((model(rays, background=bg, train=True, generator=g).rgb - target) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        after = ((model(rays, background=bg).rgb - target) ** 2).mean().item()
    assert after < before / 4, (before, after)  # about 8x on this seed; untrained stays ~0.08


# -- transfer: freezing ----------------------------------------------------------------------


@pytest.mark.parametrize("k", [2, 4, 7])  # 2 of the 3 trunk layers; the geometry; all 7 layers
def test_freeze_first_leaves_exactly_the_frozen_parameters_unchanged(k):
    model = _model()
    frozen = set(model.freeze_first(k))
    assert frozen == {n for layer in model.layers()[:k] for n in layer.param_names}
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    trainable = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.Adam(trainable, lr=1e-2) if trainable else None
    rays = _rays(16)
    g = torch.Generator().manual_seed(0)
    for _ in range(3):
        out = model(rays, background=WHITE, train=True, generator=g)
        if opt is None:
            assert not out.rgb.requires_grad
            break
        loss = ((out.rgb - rays.target) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    for name, p in model.named_parameters():
        if name in frozen:
            assert torch.equal(p, before[name]) and p.grad is None, name
        else:
            assert not torch.equal(p, before[name]), name


def test_freeze_first_out_of_range_names_the_layers():
    with pytest.raises(ConfigError, match=r"trunk\.0.*choose 0\.\.7"):
        _model().freeze_first(8)


# -- importance sampling ---------------------------------------------------------------------


@pytest.mark.parametrize("train", [False, True])
def test_importance_sampling_renders_the_union_of_sorted_samples(train):
    config = dataclasses.replace(TINY, n_samples=10, n_importance=7)
    model = _model(config)
    rays = _rays(9)
    out = model(rays, background=WHITE, train=train, generator=torch.Generator().manual_seed(0))
    assert out.samples_evaluated == 9 * (10 + 7)
    assert out.rgb.shape == (9, 3) and out.extras["rgb_coarse"].shape == (9, 3)
    t = out.extras["t"]
    assert t.shape == (9, 17) and out.extras["weights"].shape == (9, 17)
    assert (t.diff(dim=-1) >= 0).all()
    assert ((t >= rays.near[:, None]) & (t <= rays.far[:, None])).all()
    torch.testing.assert_close(out.extras["weights"].sum(-1), out.acc)
    plain = _model(dataclasses.replace(config, n_importance=0))(rays, background=WHITE)
    assert plain.samples_evaluated == 9 * 10 and "rgb_coarse" not in plain.extras


def test_importance_samples_concentrate_where_the_coarse_weights_are():
    # an opaque slab around z = 0 seen head-on from z = 3: the coarse pass stops in the bin
    # [2.75, 3.0], and every importance sample lands in it
    config = NerfMLPConfig(pos_freqs=0, depth=1, width=3, skips=(), view_dependent=False, n_samples=16,
                           n_importance=16)
    model = _model(config)
    with torch.no_grad():  # raw = 1e3 * hat(z) - 50, hat(z) = relu(z + .25) - 2 relu(z) + relu(z - .25)
        model.trunk[0].weight.copy_(torch.tensor([[0.0, 0.0, 1.0]] * 3))
        model.trunk[0].bias.copy_(torch.tensor([0.25, 0.0, -0.25]))
        model.density.weight.copy_(torch.tensor([[1e3, -2e3, 1e3]]))
        model.density.bias.fill_(-50.0)
    origins = torch.tensor([0.0, 0.0, 3.0]).expand(4, 3)
    rays = RayBatch(origins, torch.tensor([0.0, 0.0, -1.0]).expand(4, 3), torch.full((4,), 1.0), torch.full((4,), 5.0))
    out = model(rays, background=WHITE)
    assert (out.acc > 0.99).all()
    t = out.extras["t"]
    assert (((t >= 2.75) & (t <= 3.0)).sum(-1) == 1 + 16).all()  # one coarse sample, all fine ones


# -- functional calls and meta-learning ------------------------------------------------------


def test_functional_call_uses_the_given_parameters():
    model = _model()
    rays = _rays(8)
    params = dict(model.named_parameters())
    same = functional_call(model, params, (rays,), {"background": WHITE})
    assert torch.equal(same.rgb, model(rays, background=WHITE).rgb)
    changed = dict(params, **{"trunk.0.weight": params["trunk.0.weight"] + 0.1})
    other = functional_call(model, changed, (rays,), {"background": WHITE})
    assert not torch.allclose(other.rgb, same.rgb)
    assert torch.equal(model.trunk[0].weight, params["trunk.0.weight"])  # the module is untouched


def _adapted_loss(model, params, rays, inner_lr=0.5, create_graph=True):
    """One MAML inner step on ``rays``, then the loss of the adapted parameters on the same rays."""
    def loss_of(p):
        out = functional_call(model, p, (rays,), {"background": WHITE})
        return ((out.rgb - rays.target) ** 2).mean()

    grads = torch.autograd.grad(loss_of(params), list(params.values()), create_graph=create_graph)
    adapted = {n: p - inner_lr * g for (n, p), g in zip(params.items(), grads)}
    return loss_of(adapted)


@pytest.mark.parametrize("n_importance", [0, 4])
def test_second_order_gradients_flow_through_forward(n_importance):
    model = _model(dataclasses.replace(TINY, n_importance=n_importance))
    rays = _rays(16)
    params = dict(model.named_parameters())
    meta = torch.autograd.grad(_adapted_loss(model, params, rays), list(params.values()))
    first_order = torch.autograd.grad(_adapted_loss(model, params, rays, create_graph=False), list(params.values()))
    assert all(torch.isfinite(g).all() for g in meta)
    assert all(g.abs().sum() > 0 for g in meta)
    assert any(not torch.allclose(a, b) for a, b in zip(meta, first_order))  # the second-order term counts


def test_second_order_gradient_matches_finite_differences():
    # no importance pass here: its sample positions move with the parameters without a gradient
    # (detached, as in NeRF), which finite differences would see
    config = NerfMLPConfig(pos_freqs=2, dir_freqs=1, depth=2, width=6, skips=(1,), n_samples=6)
    model = _model(config, BOX.double())
    rays = _rays(4, dtype=torch.float64)
    params = dict(model.named_parameters())

    def meta_loss(w_trunk, w_density):
        p = dict(params, **{"trunk.0.weight": w_trunk, "density.weight": w_density})
        return _adapted_loss(model, p, rays)

    inputs = (params["trunk.0.weight"].clone().requires_grad_(), params["density.weight"].clone().requires_grad_())
    assert torch.autograd.gradcheck(meta_loss, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


# -- construction ----------------------------------------------------------------------------


def test_config_round_trips_through_json_and_rejects_bad_values():
    for config in (NERF_PAPER, NERF_SMALL, dataclasses.replace(TINY, skips=(1, 2))):
        assert NerfMLPConfig(**json.loads(json.dumps(dataclasses.asdict(config)))) == config
    for bad in ({"skips": (0,)}, {"skips": (3,)}, {"density_activation": "exp"}, {"alpha_init": 1.0},
                {"n_samples": 0}, {"n_importance": -1}, {"lr": 0.0}, {"width": 1}):
        name = next(iter(bad))
        with pytest.raises(ConfigError, match=name):
            dataclasses.replace(TINY, **bad)
    with pytest.raises(ConfigError, match="bounds"):
        NerfMLP(TINY, torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]))


def test_init_follows_the_generator_and_the_bounds_dtype():
    a, b, c = _model(seed=0), _model(seed=0), _model(seed=1)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not torch.equal(sa["trunk.0.weight"], sc["trunk.0.weight"])
    bound = 1 / math.sqrt(a.trunk[0].in_features)
    assert a.trunk[0].weight.abs().max() <= bound
    double = _model(bounds=BOX.double())
    assert all(p.dtype == torch.float64 for p in double.parameters()) and double.bounds.dtype == torch.float64
    out = double(_rays(3, dtype=torch.float64), background=WHITE.double())
    assert out.rgb.dtype == torch.float64


# -- the shipped model zoo still loads ---------------------------------------------------------


def _zoo_folders() -> list:
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "model_zoo"
    return sorted(p.parent for p in root.glob("*/**/init.json"))


@pytest.mark.parametrize("folder", _zoo_folders(), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_model_zoo_entries_load_with_their_names_and_render(folder):
    """Every shipped NeRF-MLP entry loads strictly (parameter names unchanged), renders finite colours
    through the shared compositor, and its weights also load into an occupancy-estimator model."""
    from nerfmeta.init import load_init

    saved = load_init(folder)
    model = saved.build()
    assert sorted(saved.state) == sorted(model.state_dict())
    rays = _rays(6)
    out = model(rays, background=WHITE, target=torch.full((6, 3), 0.5))
    assert torch.isfinite(out.rgb).all() and set(out.losses) == {"mse"}
    occ = NerfMLP(dataclasses.replace(saved.model_config, estimator="occupancy"), model.bounds)
    occ.load_state_dict(saved.state)  # strict: the grid is not part of the weights
    torch.testing.assert_close(occ.get_density(rays.origins)[0], model.get_density(rays.origins)[0])


# -- the occupancy-grid estimator --------------------------------------------------------------

OCC = dataclasses.replace(TINY, estimator="occupancy", occupancy_resolution=9, occupancy_warmup=2, occupancy_every=3,
                          early_stop_eps=0.0)


def _ball_field(model, radius=0.5):
    """Give ``model`` an opaque-ish ball of ``radius``: the density head reads a fixed function of the points."""
    original = model._raw_density

    def raw_density(points):
        raw, h = original(points)
        inside = (points.norm(dim=-1) < radius).to(raw.dtype)
        return raw * 0 + 20.0 * inside - 20.0 * (1 - inside), h

    model._raw_density = raw_density
    return model


def test_occupancy_warm_up_skips_nothing_then_refresh_skips_empty_space_only():
    model = _ball_field(_model(OCC))
    rays = _rays(24, seed=3)
    before = model(rays, background=WHITE)
    assert model.begin_step(1, None).message == "" and not model.occupancy.skips  # still warming up
    event = model.begin_step(2, None)
    assert not event.params_changed and "occupancy grid refreshed" in event.message and model.occupancy.skips
    after = model(rays, background=WHITE)
    assert after.samples_evaluated < 0.5 * before.samples_evaluated
    torch.testing.assert_close(after.rgb, before.rgb, rtol=0, atol=1e-4)  # only empty space was skipped
    torch.testing.assert_close(after.acc, before.acc, rtol=0, atol=1e-4)
    occupied = model.occupancy.binaries.clone()
    model.begin_step(4, None)
    assert torch.equal(model.occupancy.binaries, occupied)  # not due (every 3 after the warm-up)


def test_occupancy_early_termination_drops_samples_behind_the_surface():
    rays = _rays(24, seed=4)
    full = _ball_field(_model(OCC))(rays, background=WHITE)
    cut = _ball_field(_model(dataclasses.replace(OCC, early_stop_eps=1e-3)))(rays, background=WHITE)
    assert cut.samples_evaluated < full.samples_evaluated
    torch.testing.assert_close(cut.rgb, full.rgb, rtol=0, atol=2e-3)


def test_occupancy_structure_round_trip_restores_identical_renders():
    model = _model(OCC)
    for step in range(6):
        model.begin_step(step, None)
    fresh = _model(OCC, seed=1)
    fresh.load_structure(json.loads(json.dumps(model.structure())))
    fresh.load_state_dict(model.state_dict())
    rays = _rays(16, seed=5)
    assert torch.equal(fresh(rays, background=WHITE).rgb, model(rays, background=WHITE).rgb)


def test_occupancy_short_fit_raises_psnr_with_fewer_samples(tiny_scene):
    from nerfmeta.data import load_scene
    from nerfmeta.fit.loop import FitConfig, fit

    scene = load_scene(tiny_scene)
    config = dataclasses.replace(OCC, occupancy_resolution=24, occupancy_warmup=20, occupancy_every=20, n_samples=24,
                                 early_stop_eps=1e-4, lr=5e-3)
    model = NerfMLP(config, scene.bounds, generator=torch.Generator().manual_seed(0))
    result = fit(model, scene, FitConfig(iters=80, batch_rays=256, eval_every=0, final_ssim=False), background=WHITE)
    first, last = result.history[0], result.history[-1]
    assert last.train_psnr > first.train_psnr + 3.0
    assert model.occupancy.size == (24, 24, 24)  # refreshed during the fit
    assert result.final.samples_per_ray < 0.5 * config.n_samples  # the box only, not all of [near, far]


def test_importance_sampling_needs_the_stratified_estimator():
    with pytest.raises(ConfigError, match="estimator=stratified"):
        dataclasses.replace(OCC, n_importance=4)
