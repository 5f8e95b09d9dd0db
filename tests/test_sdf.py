"""The SDF backbone: NeuS's opacity, geometric initialisation, gradients, named losses, meta-learning."""

import math

import pytest
import torch
import torch.nn.functional as F

from nerfmeta.data.scene import RayBatch
from nerfmeta.errors import ConfigError
from nerfmeta.fields.base import check_partition, total_loss
from nerfmeta.fields.registry import build_model
from nerfmeta.fields.sdf import SdfConfig, annealed_cos, neus_tau, ramped_weight
from nerfmeta.render.estimators import dilate, grid_points

TINY = SdfConfig(depth=2, width=32, feature_dim=4, color_depth=1, color_width=8, n_samples=16, pos_freqs=2, dir_freqs=1,
                 occupancy=False, hash_levels=3, hash_log2_size=8, hash_base_res=2, hash_finest_res=16, nffb_width=4,
                 fourier_features=8)
BOX = torch.tensor([[-1.0] * 3, [1.0] * 3])


def rays(n: int = 16, seed: int = 0, alpha: bool = False) -> RayBatch:
    gen = torch.Generator().manual_seed(seed)
    origins = F.normalize(torch.randn(n, 3, generator=gen), dim=-1) * 3.0
    dirs = F.normalize(0.3 * torch.randn(n, 3, generator=gen) - origins, dim=-1)
    target = torch.rand(n, 3, generator=gen)
    mask = (torch.rand(n, generator=gen) > 0.5).float() if alpha else None
    return RayBatch(origins, dirs, torch.full((n,), 1.0), torch.full((n,), 5.0), target, mask)


def test_neus_tau_matches_the_alpha_form_in_float64():
    gen = torch.Generator().manual_seed(0)
    sdf = torch.randn(200, generator=gen, dtype=torch.float64) * 0.2
    cos = -torch.rand(200, generator=gen, dtype=torch.float64)
    delta = torch.rand(200, generator=gen, dtype=torch.float64) * 0.1
    s = torch.tensor(40.0, dtype=torch.float64)
    prev_cdf = torch.sigmoid(s * (sdf - 0.5 * cos * delta))
    next_cdf = torch.sigmoid(s * (sdf + 0.5 * cos * delta))
    alpha = ((prev_cdf - next_cdf) / prev_cdf).clamp(0.0, 1.0)  # NeuS's formula, without its 1e-5
    torch.testing.assert_close(-torch.expm1(-neus_tau(sdf, cos, delta, s)), alpha, rtol=1e-10, atol=1e-12)


def test_neus_tau_is_zero_going_out_and_finite_far_inside():
    s = torch.tensor(1e6)
    tau = neus_tau(torch.tensor([0.5, -50.0, 0.0]), torch.tensor([0.0, -1.0, -1.0]), torch.tensor([0.1, 0.1, 0.1]), s)
    assert tau[0] == 0.0 and torch.isfinite(tau).all() and tau[2] > 10.0  # a crossing at this s is opaque


def test_annealed_cos_exact_small_case():
    cos = torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0])
    torch.testing.assert_close(annealed_cos(cos, 0.0), torch.tensor([-1.0, -0.75, -0.5, -0.25, 0.0]))
    torch.testing.assert_close(annealed_cos(cos, 0.5), torch.tensor([-1.0, -0.625, -0.25, -0.125, 0.0]))
    torch.testing.assert_close(annealed_cos(cos, 1.0), torch.tensor([-1.0, -0.5, 0.0, 0.0, 0.0]))


def test_cos_anneal_follows_the_steps_and_softens_back_faces():
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "cos_anneal_iters": 100}), BOX, seed=0)
    assert model.cos_anneal_ratio == 1.0  # a model no fit steps renders exactly
    model.begin_step(0, None)
    assert model.cos_anneal_ratio == 0.0
    with torch.no_grad():
        soft = model(rays(), background=torch.ones(3)).acc
    model.begin_step(25, None)
    assert model.cos_anneal_ratio == 0.25
    model.begin_step(500, None)
    assert model.cos_anneal_ratio == 1.0
    with torch.no_grad():
        exact = model(rays(), background=torch.ones(3)).acc
    assert bool((soft >= exact - 1e-6).all()) and float((soft - exact).max()) > 1e-3  # leaving sections are partly opaque


@pytest.mark.parametrize("encoding", ["pe", "fourier", "hash", "nffb", "stylemod-nffb"])
def test_geometric_init_is_a_sphere_inside_out(encoding):
    model = build_model("sdf", SdfConfig(encoding=encoding), BOX, seed=0)
    sdf = model.sdf_world(torch.tensor([[0.0, 0.0, 0.0], [0.95, 0.0, 0.0], [0.0, -0.95, 0.0], [0.0, 0.0, 0.95]]))
    assert sdf[0] < -0.2 and bool((sdf[1:] > 0.1).all())


def test_sdf_is_in_world_units_at_any_scale():
    a = build_model("sdf", TINY, BOX, seed=1)
    b = build_model("sdf", TINY, BOX * 1000.0, seed=1)
    p = torch.tensor([[0.1, 0.2, -0.3]])
    torch.testing.assert_close(b.sdf_world(p * 1000.0), a.sdf_world(p) * 1000.0, rtol=1e-4, atol=1e-4)


def test_numerical_gradient_matches_analytic_for_a_smooth_encoding():
    model = build_model("sdf", TINY, BOX, seed=0).double()  # float64: float32 differences are off by ~1e-3 near softplus kinks
    x = torch.rand(50, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5
    analytic = model.evaluate(x).grad
    tetra = model._numerical(x, 1e-5, False).grad
    central = model._numerical(x, 1e-5, True).grad
    torch.testing.assert_close(tetra, analytic, rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(central, analytic, rtol=1e-3, atol=1e-4)


@pytest.mark.parametrize("encoding,pos_freqs", [("pe", 2), ("pe", 0), ("fourier", 2), ("nffb", 2)])
def test_the_written_out_chain_rule_is_autograds_gradient_and_second_order(encoding, pos_freqs):
    """Training's gradient (:meth:`SdfField._sdf_with_gradient`) against autograd's ``create_graph`` one in float64: the same
    ``grad f``, and the same parameter gradients of an eikonal + sdf loss (the second-order path the fit trains through)."""
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "encoding": encoding, "pos_freqs": pos_freqs, "gradient": "analytic"}),
                        BOX, seed=0).double()
    x = torch.rand(64, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 1.6 - 0.8

    def loss_and_grads(sdf, grad):
        loss = ((grad.norm(dim=-1) - 1.0) ** 2).mean() + sdf.square().mean()
        return grad, torch.autograd.grad(loss, [p for p in model.parameters() if p.requires_grad], allow_unused=True)

    xg = x.clone().requires_grad_(True)
    sdf, _ = model.sdf_and_feature(xg)
    (grad,) = torch.autograd.grad(sdf.sum(), xg, create_graph=True)
    ref_grad, ref = loss_and_grads(sdf, grad)
    ev = model.evaluate(x)
    new_grad, new = loss_and_grads(ev.sdf, ev.grad)
    # softplus is linear past 100 z = 20, where its slope is 1 and the sigmoid's 1 - 2e-9: agreement to ~1e-7
    torch.testing.assert_close(new_grad, ref_grad, rtol=1e-6, atol=1e-9)
    for a, b in zip(new, ref):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-9)


def test_tetrahedral_gradient_is_exact_for_a_linear_function():
    from nerfmeta.fields.sdf import TETRAHEDRON

    v = torch.tensor(TETRAHEDRON, dtype=torch.float64)
    g = torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64)
    x = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    f = (x + 0.01 * v) @ g
    torch.testing.assert_close((v * f[:, None]).sum(0) / (4 * 0.01), g)


def test_losses_are_named_terms_and_every_parameter_learns():
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "curvature_weight": 0.01}), BOX, seed=0)
    check_partition(model)
    batch = rays(alpha=True)
    out = model(batch, background=torch.ones(3), train=True, generator=torch.Generator().manual_seed(0), target=batch.target)
    assert set(out.losses) == {"mse", "eikonal", "mask", "curvature"}
    total_loss(out.losses).backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


def test_the_variance_has_its_own_learning_rate():
    """``variance_lr`` sets how fast the logistic sharpens: one Adam step moves ``s`` by ``exp(10 variance_lr)``."""
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "variance_lr": 0.02, "lr": 1e-4}), BOX, seed=0)
    groups = {g.name: g for g in model.param_groups()}
    assert groups["variance"].param_names == ("variance",) and groups["variance"].lr == 0.02
    assert "variance" not in groups["sdf"].param_names and groups["sdf"].lr == 1e-4
    check_partition(model)
    opt = torch.optim.Adam([{"params": [model.get_parameter(n) for n in g.param_names], "lr": g.lr} for g in groups.values()])
    s0 = float(model.inv_s().detach())
    batch = rays(alpha=True)
    out = model(batch, background=torch.ones(3), train=True, generator=torch.Generator().manual_seed(0), target=batch.target)
    total_loss(out.losses).backward()
    opt.step()
    assert float(model.inv_s().detach()) / s0 == pytest.approx(math.exp(10 * 0.02 * -math.copysign(1.0, float(model.variance.grad))), rel=1e-3)


@pytest.mark.parametrize("view_dependent", [True, False])
def test_a_diffuse_colour_ignores_the_view_direction(view_dependent):
    """``view_dependent=False``: the colour at a point is the same from every direction (it cannot fake parallax)."""
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "view_dependent": view_dependent}), BOX, seed=0)
    for layer in model.color:
        torch.nn.init.normal_(layer.weight, 0.0, 1.0)
    points = torch.rand(5, 3) - 0.5
    with torch.no_grad():
        _, emb = model.get_density(points)
        a = model.get_outputs(emb, None, F.normalize(torch.randn(5, 3), dim=-1), torch.arange(5))
        b = model.get_outputs(emb, None, F.normalize(torch.randn(5, 3), dim=-1), torch.arange(5))
    assert torch.equal(a, b) != view_dependent


def test_the_colour_network_can_see_an_encoded_position():
    """``color_pos_freqs=k`` feeds ``[x, sin/cos(2^j pi x)]`` (3 + 6k columns) to the colour network; 0 is NeuS's raw ``x``."""
    widths = {k: build_model("sdf", SdfConfig(**{**TINY.__dict__, "color_pos_freqs": k}), BOX, seed=0).color[0].in_features
              for k in (0, 3)}
    assert widths[3] - widths[0] == 18
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "color_pos_freqs": 3}), BOX, seed=0)
    batch = rays()
    out = model(batch, background=torch.ones(3), train=True, generator=torch.Generator().manual_seed(0), target=batch.target)
    total_loss(out.losses).backward()
    assert model.color[0].weight.grad[:, 3:21].abs().sum() > 0


def test_a_colour_grid_stores_texture_apart_from_the_sdf():
    """``color_grid=S``: an (color_grid_dim, S, S, S) grid over the box frame feeds the colour network its trilinear
    features, learns at its own rate, and leaves the SDF network's inputs and the state of ``color_grid=0`` unchanged."""
    plain = build_model("sdf", SdfConfig(**{**TINY.__dict__, "view_dependent": False}), BOX, seed=0)
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "view_dependent": False, "color_grid": 5, "color_grid_dim": 3, "color_grid_lr": 0.2}), BOX, seed=0)
    assert "color_grid" not in dict(plain.named_parameters())
    assert tuple(model.color_grid.shape) == (3, 5, 5, 5)
    assert model.color[0].in_features - plain.color[0].in_features == 3
    groups = {g.name: g for g in model.param_groups()}
    assert groups["color_grid"].param_names == ("color_grid",) and groups["color_grid"].lr == 0.2
    assert "color_grid" not in groups["sdf"].param_names
    check_partition(model)
    batch = rays(alpha=True)
    out = model(batch, background=torch.ones(3), train=True, generator=torch.Generator().manual_seed(0), target=batch.target)
    total_loss(out.losses).backward()
    assert model.color_grid.grad.abs().sum() > 0  # zero-initialised, yet it learns from the first step
    # Exact small case: at a grid corner the features are that corner's values; the SDF does not see the grid.
    with torch.no_grad():
        model.color_grid.normal_()
        corner = torch.tensor([[0.5, -1.0, 0.0]])  # box-frame corner (3, 0, 2) of a 5-corner grid over [-1, 1]
        _, emb = model.get_density(corner)
        h = model.color_grid[:, 3, 0, 2]
        assert torch.equal(emb.sdf, plain.get_density(corner)[1].sdf)
        first = model.color[0](torch.cat([corner, F.normalize(emb.grad, dim=-1), h[None], emb.feature], -1))
        hidden = F.relu(first)
        for layer in model.color[1:-1]:
            hidden = F.relu(layer(hidden))
        torch.testing.assert_close(model.get_outputs(emb, None, torch.zeros(1, 3), torch.zeros(1, dtype=torch.long)),
                                   torch.sigmoid(model.color[-1](hidden)))
    with pytest.raises(ConfigError, match="color_grid"):
        SdfConfig(color_grid=1)


def test_no_mask_term_without_alpha_and_eikonal_weight_applies():
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "eikonal_weight": 0.0}), BOX, seed=0)
    batch = rays()
    out = model(batch, background=torch.ones(3), target=batch.target)
    assert set(out.losses) == {"mse"}


def test_ramped_weight_exact_small_cases():
    assert ramped_weight(0, -1.0, 0.1, (0, 0)) == 0.1  # no ramp: the final weight throughout
    assert [ramped_weight(s, 0.01, 0.1, (10, 20)) for s in (0, 10, 15, 20, 99)] == pytest.approx([0.01, 0.01, 0.055, 0.1, 0.1])
    assert [ramped_weight(s, 0.0, 1.0, (5, 5)) for s in (4, 5, 6)] == [0.0, 1.0, 1.0]  # a switch
    assert [ramped_weight(p, 0.001, 0.1, (0.4, 0.6)) for p in (0.0, 0.4, 0.5, 0.6, 1.0)] == pytest.approx([0.001, 0.001, 0.0505, 0.1, 0.1])


def test_the_eikonal_term_follows_its_ramp():
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "eikonal_weight": 0.1, "eikonal_start_weight": 0.01,
                                             "eikonal_ramp": (10, 20)}), BOX, seed=0)
    batch = rays()
    terms = {}
    for step in (0, 15, 30):
        model.begin_step(step, None)
        out = model(batch, background=torch.ones(3), target=batch.target)
        grad_term = float(out.losses["eikonal"].detach()) / model.eikonal_now
        terms[step] = (model.eikonal_now, grad_term)
    assert [w for w, _ in terms.values()] == pytest.approx([0.01, 0.055, 0.1])
    assert terms[0][1] == pytest.approx(terms[30][1], rel=1e-5)  # same parameters, same (|grad f| - 1)^2: only the weight moved
    with pytest.raises(ConfigError, match="eikonal_ramp"):
        SdfConfig(eikonal_ramp=(20, 10))
    with pytest.raises(ConfigError, match="eikonal_start_weight"):  # a start weight without a ramp would never be used
        SdfConfig(eikonal_start_weight=0.01)
    unstepped = build_model("sdf", model.config, BOX, seed=0)
    assert unstepped.eikonal_now == 0.1  # a model no fit steps uses the final weight, as the cos anneal


def test_a_ramp_in_fractions_of_the_fit_follows_its_progress_not_its_steps():
    config = SdfConfig(**{**TINY.__dict__, "eikonal_weight": 0.1, "eikonal_start_weight": 0.001, "eikonal_ramp_progress": (0.4, 0.6)})
    model = build_model("sdf", config, BOX, seed=0)
    seen = []
    for step, progress in ((0, 0.0), (10, 0.4), (10, 0.5), (10_000, 0.5), (20, 0.6), (20, 1.0)):
        model.begin_step(step, progress)
        seen.append(model.eikonal_now)
    assert seen == pytest.approx([0.001, 0.001, 0.0505, 0.0505, 0.1, 0.1])  # the step count plays no part
    model.begin_step(0, None)  # stepped outside a fit with a planned end: no progress, the final weight
    assert model.eikonal_now == 0.1


@pytest.mark.parametrize("bad", [
    {"eikonal_ramp_progress": (0.6, 0.4)},  # backwards
    {"eikonal_ramp_progress": (0.4, 1.5)},  # past the end of the fit
    {"eikonal_ramp_progress": (0.4, 0.6), "eikonal_ramp": (10, 20)},  # two ramps for one weight
])
def test_a_ramp_in_fractions_is_refused_when_it_cannot_mean_one_thing(bad):
    with pytest.raises(ConfigError, match="eikonal_ramp"):
        SdfConfig(eikonal_start_weight=0.01, **bad)


def test_eval_render_needs_no_autograd_and_keeps_no_graph():
    model = build_model("sdf", TINY, BOX, seed=0)
    with torch.no_grad():
        out = model(rays(), background=torch.ones(3))
    assert not out.rgb.requires_grad and torch.isfinite(out.rgb).all()
    assert bool(((out.acc >= 0) & (out.acc <= 1)).all())


def test_occupancy_refresh_keeps_the_surface():
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "occupancy": True, "occupancy_warmup": 0, "occupancy_resolution": 32, "n_samples": 64}), BOX, seed=0)
    model.begin_step(0, 10)
    frac = model.occupancy.occupied_fraction()
    assert 0.0 < frac < 0.8
    with torch.no_grad():
        out = model(rays(), background=torch.ones(3))
    assert out.samples_evaluated > 0 and float(out.acc.max()) > 0.5


def test_a_narrower_occupancy_margin_marches_a_narrower_band_that_still_holds_the_surface():
    def occupied(margin: float) -> tuple[float, torch.Tensor]:
        config = SdfConfig(**{**TINY.__dict__, "occupancy": True, "occupancy_warmup": 0, "occupancy_resolution": 32,
                              "n_samples": 64, "occupancy_margin": margin, "init_variance": 0.6})  # s = 403: a sharp surface
        model = build_model("sdf", config, BOX, seed=0)
        model.begin_step(0, None)
        with torch.no_grad():
            return model.occupancy.occupied_fraction(), model(rays(), background=torch.ones(3)).acc

    wide, acc_wide = occupied(3.0)
    narrow, acc_narrow = occupied(1.0)
    assert 0.0 < narrow < 0.75 * wide
    torch.testing.assert_close(acc_narrow, acc_wide, atol=2e-3, rtol=0.0)  # the band still holds every crossing
    with pytest.raises(ConfigError, match="occupancy_margin"):
        SdfConfig(occupancy_margin=0.0)


def test_narrow_refreshes_mark_what_full_ones_would_and_a_jump_brings_full_ones_back():
    config = SdfConfig(**{**TINY.__dict__, "occupancy": True, "occupancy_warmup": 0, "occupancy_every": 1, "occupancy_resolution": 32,
                          "n_samples": 64, "occupancy_margin": 1.0, "occupancy_reach": 2.0, "occupancy_full_every": 4})
    model = build_model("sdf", config, BOX, seed=0)
    cell = 2.0 / 31
    band = cell + 2.0 / 64
    corners = model.to_box(grid_points(model.occupancy.aabb, (32,) * 3).reshape(-1, 3))

    def full_marks() -> torch.Tensor:
        with torch.no_grad():
            return dilate((model.sdf_and_feature(corners)[0].abs() < band).view(32, 32, 32), 1)

    def grow(cells: float) -> None:  # a constant shift moves |f| by at most that much everywhere
        with torch.no_grad():
            model.sdf[-1].bias[0] -= cells * cell

    narrow = []
    for step in range(12):  # half a cell per refresh: never more than the reach between full refreshes
        grow(0.5)
        evaluated = model.band.evaluated
        model.begin_step(step, None)
        assert torch.equal(model.occupancy.binaries, full_marks())
        narrow.append(model.band.evaluated - evaluated)
    assert model.band.missed == 0 and model.band.period == 4 and model.band.full < 12
    assert min(narrow) < 0.5 * 32 ** 3 and max(narrow) == 32 ** 3
    while model.band.since_full + 1 >= model.band.period:  # the next refresh is a narrow one
        model.begin_step(12, None)
    grow(6.0)  # a jump beyond the reach
    model.begin_step(13, None)
    while model.band.since_full:  # narrow refreshes until the next full one
        model.begin_step(14, None)
    assert model.band.missed > 0 and model.band.period == 1
    assert torch.equal(model.occupancy.binaries, full_marks())
    copy = build_model("sdf", config, BOX, seed=1)
    copy.begin_step(0, None)
    copy.load_state_dict(model.state_dict())  # new weights: remembered distances no longer hold
    assert copy.band.distance is None and copy.band.corners is None and copy.band.period == 1


def test_a_wall_thinner_than_the_step_is_opaque_once_its_sections_are_split():
    """NeuS's opacity of a slab 0.02 thick marched every 0.05: where no sample falls inside it, light leaks through; splitting
    the sections within a step of the surface makes it as opaque as NeuS's logistic lets it be at every jitter (float64, exact SDF)."""
    from nerfmeta.render.estimators import PackedSamples, march_packed, split_sections

    jitter = torch.linspace(0.0, 0.99, 50, dtype=torch.float64)
    near, far = torch.zeros(50, dtype=torch.float64), torch.ones(50, dtype=torch.float64)
    coarse = PackedSamples(*march_packed(near, far, 0.05, jitter), far)

    def transmittance(s: PackedSamples) -> torch.Tensor:
        sdf = (s.t - 0.5).abs() - 0.01  # the slab [0.49, 0.51]; the ray is its normal
        cos = torch.where(s.t < 0.5, -1.0, 1.0).to(s.t).clamp(max=0.0)
        tau = neus_tau(sdf, cos, s.delta, torch.tensor(400.0, dtype=torch.float64))
        return torch.exp(-torch.zeros(50, dtype=torch.float64).index_add(0, s.ray_idx, tau))

    before = transmittance(coarse)
    coarse_sdf = (coarse.t - 0.5).abs() - 0.01
    after = transmittance(split_sections(coarse, coarse_sdf.abs() < coarse.delta, 8))
    floor = 1.0 / (1.0 + math.exp(4.0))  # sigmoid(-s * half-thickness): what NeuS's logistic lets through at best
    assert float(before.max()) > 0.9  # a ray with no sample in the wall sees through it
    assert float(after.max()) < 4.0 * floor and float(after.mean()) < 1.3 * floor


def test_refine_splits_only_the_sections_near_the_surface():
    base = build_model("sdf", TINY, BOX, seed=0)
    refined = build_model("sdf", SdfConfig(**{**TINY.__dict__, "refine": 4}), BOX, seed=0)
    r = rays()
    plain, split = base.sample(r, train=False, generator=None).samples, refined.sample(r, train=False, generator=None).samples
    with torch.no_grad():
        near_surface = base.sdf_and_feature(base.to_box(plain.points(r.origins, r.directions)))[0].abs() < plain.delta  # h = 1
    assert 0 < int(near_surface.sum()) < len(plain) and len(split) == len(plain) + 3 * int(near_surface.sum())
    torch.testing.assert_close(torch.zeros(len(r)).index_add(0, split.ray_idx, split.delta),
                               torch.zeros(len(r)).index_add(0, plain.ray_idx, plain.delta))
    with pytest.raises(ConfigError, match="refine"):
        SdfConfig(refine=0)


def test_bad_settings_are_refused():
    with pytest.raises(ConfigError, match="gradient"):
        SdfConfig(gradient="symbolic")
    with pytest.raises(ConfigError, match="encoding"):
        SdfConfig(encoding="wavelet")


def test_meta_learning_works_on_the_sdf():
    """Weight-space meta-learning needs nothing special: MAML's meta-gradient reaches every parameter."""
    from pretrain.meta import MetaConfig, Task, maml_meta_grad, meta_wrapper

    config = MetaConfig(backbone="sdf", algo="maml", model={"depth": 2, "width": 16, "feature_dim": 4, "pos_freqs": 2, "n_samples": 8})
    config.validate()
    model_config = config.model_config()
    assert model_config.occupancy is False
    model = build_model("sdf", model_config, BOX, seed=0)
    task = Task("t", rays(8, 1), rays(8, 2), 3)
    grads, adaptation = maml_meta_grad(meta_wrapper(model, "torchfunc", 0.5, first_order=False), list(model.parameters()),
                                       task, 1, background=torch.ones(3))
    assert math.isfinite(float(adaptation.query_mse.detach()))
    for (name, _), g in zip(model.named_parameters(), grads):
        assert torch.isfinite(g).all(), name
    assert sum(float(g.abs().sum()) for g in grads) > 0


def test_fit_cli_on_the_tiny_scene(tiny_scene, tmp_path):
    from nerfmeta.cli import main

    out = tmp_path / "run"
    code = main(["fit", str(tiny_scene), "--out", str(out), "--backbone", "sdf", "--iters", "4", "--batch-rays", "64",
                 "--eval-every", "4", "--renders", "0", "--eval-views", "1",
                 "--set", "depth=2", "--set", "width=16", "--set", "n_samples=16", "--set", "encoding=hash",
                 "--set", "hash_levels=2", "--set", "hash_log2_size=8"])
    assert code == 0 and (out / "summary.json").exists()


def test_stiff_surface_cases_stay_finite(tmp_path):
    """The stress table's surface rows, small: a scene at 1000x scale, a 4-entry hash table, Fourier sigma 1e3."""
    import dataclasses

    from benchlib.stress import CASES, QUICK, check_results, run_case

    small = dataclasses.replace(QUICK, n_train=4, fit=dataclasses.replace(QUICK.fit, iters=25))
    names = ("sdf (reference)", "sdf, poses x 1e3", "hash table of 4 entries", "Fourier sigma 1e3")
    cases = [c for c in CASES if c.name in names]
    results = [run_case(c, "sdf", small, tmp_path) for c in cases]
    check_results(results, cases)
    for r in results:
        assert not r.nan_seen and r.test_psnr is not None and math.isfinite(r.test_psnr), (r.case, r.outcome)
    by_name = {r.case: r for r in results}
    assert abs(by_name["sdf, poses x 1e3"].psnr_gap) < 0.5  # the same fit at 1000x the scale


def test_the_thin_shell_term_is_the_samples_inside_probability_and_shrinks_the_solid():
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "shell_weight": 0.5}), BOX, seed=0)
    batch = rays(64)
    gen = torch.Generator().manual_seed(0)
    out = model(batch, background=torch.ones(3), train=True, generator=gen, target=batch.target)
    inside = out.extras["inside"]
    assert out.losses["shell"].item() == pytest.approx(0.5 * inside.mean().item())
    assert 0.0 < inside.mean().item() < 1.0  # the rays cross the initial sphere: samples inside and out
    # the term alone moves the surface into the solid: f rises at the sphere's centre
    centre = torch.zeros(1, 3)
    before = model.sdf_and_feature(model.to_box(centre))[0].item()
    opt = torch.optim.SGD([p for n, p in model.named_parameters() if n != "variance"], lr=1e-2)
    for _ in range(20):
        opt.zero_grad()
        out = model(batch, background=torch.ones(3), train=True, generator=gen, target=batch.target)
        out.losses["shell"].backward()
        opt.step()
    assert model.sdf_and_feature(model.to_box(centre))[0].item() > before
    # off by default, and never in a render that does not train
    assert "shell" not in build_model("sdf", TINY, BOX, seed=0)(batch, background=torch.ones(3), train=True,
                                                                 generator=gen, target=batch.target).losses
    assert "inside" not in model(batch, background=torch.ones(3)).extras


def test_the_shell_prior_fades_out_over_its_fractions_of_the_fit():
    model = build_model("sdf", SdfConfig(**{**TINY.__dict__, "shell_weight": 0.5, "shell_fade_progress": (0.5, 0.75)}), BOX, seed=0)
    batch = rays(64)
    weights, terms = [], []
    for progress in (0.0, 0.5, 0.625, 0.75, 1.0):
        model.begin_step(100, progress)
        out = model(batch, background=torch.ones(3), train=True, generator=torch.Generator().manual_seed(0), target=batch.target)
        weights.append(model.shell_now)
        terms.append(out.losses["shell"].item() / model.shell_now if "shell" in out.losses else None)
    assert weights == pytest.approx([0.5, 0.5, 0.25, 0.0, 0.0])
    assert terms[0] == pytest.approx(terms[2], rel=1e-6) and terms[3:] == [None, None]  # the weight moves, not the term; at 0 no term
    model.begin_step(100, None)  # stepped without a planned end: the prior as set
    assert model.shell_now == 0.5
    for fade in ((0.8, 0.6), (0.5, 1.5), (0.5,)):
        with pytest.raises(ConfigError, match="shell_fade_progress"):
            SdfConfig(shell_fade_progress=fade)
