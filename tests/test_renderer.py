"""The paper's claims about the rendering weight, checked on analytic fields (no training).

A ray p(t) = t v crosses planes at known depths; the UDF along it is the distance to the nearest plane.
"""

import math

import pytest
import torch

from neudf_core.normals import regularised_normals
from neudf_core.renderer import alpha_for_mode, section_ends, varsigma, weights_from_alpha
from neudf_core.sampler import hierarchical_samples, importance_weights

COS = math.cos(math.radians(30))  # the ray meets the planes at 30 degrees from their normal


def plane_udf(t: torch.Tensor, hits: list[float]) -> tuple[torch.Tensor, torch.Tensor]:
    """UDF along the ray and its directional derivative, for planes crossed at depths ``hits``."""
    offsets = torch.stack([t - h for h in hits])
    nearest = offsets.abs().argmin(0)
    signed = offsets.gather(0, nearest[None])[0]
    return COS * signed.abs(), COS * torch.sign(signed)


def render_weights(hits, mode, sharpness, n=2000, t0=0.0, t1=4.0, kind="rational"):
    """Dense sections on [t0, t1]; returns (section mid-points, weights)."""
    z = torch.linspace(t0, t1, n + 1, dtype=torch.float64)[None]
    dists = z[:, 1:] - z[:, :-1]
    mid = z[:, :-1] + dists / 2
    psi, slope = plane_udf(mid, hits)
    signed = mode == "neus_sdf"
    prev, nxt = section_ends(psi, slope, dists, cos_anneal=1.0, signed=signed)
    alpha = alpha_for_mode(mode, prev, nxt, torch.tensor(sharpness, dtype=torch.float64), kind)
    weights, _ = weights_from_alpha(alpha)
    return mid[0], weights[0]


def mass_near(mid, weights, depth, band=0.05):
    return float(weights[(mid - depth).abs() < band].sum())


@pytest.mark.parametrize("r", [1.0, 10.0, 100.0, 1000.0])
def test_neudf_weight_peaks_at_the_intersection(r):
    mid, w = render_weights([2.0], "neudf", r)
    assert abs(float(mid[w.argmax()]) - 2.0) < 2 * (4.0 / 2000)


def test_neudf_mass_concentrates_on_the_first_of_two_surfaces():
    masses = [mass_near(*render_weights([1.5, 2.5], "neudf", r), 1.5) for r in (1.0, 10.0, 100.0, 1000.0, 1e4)]
    assert all(b >= a - 1e-9 for a, b in zip(masses, masses[1:])), masses  # grows with r
    assert masses[-1] > 0.95
    assert masses[-2] > 0.9
    mid, w = render_weights([1.5, 2.5], "neudf", 1e4)
    assert mass_near(mid, w, 2.5) < 0.02  # the hidden surface gets almost nothing


def front_offset(mid, weights, depth):
    """How far in front of ``depth`` the composited colour comes from: the weights' mean depth."""
    return depth - float((weights * mid).sum() / weights.sum())


def test_neudf_weight_lies_in_front_of_the_surface_about_one_over_r_deep():
    # Transmittance reaches 0 at the first hit, so all the weight lies on the near side and the colour
    # is composited from in front of the zero level. With varsigma = 1 - e^{-r d} the mean is 1/r along
    # the UDF; the rational varsigma's 1/(1 + r d) tail puts it several times deeper.
    offsets = {}
    for kind in ("exp", "rational"):
        for r in (100.0, 400.0):
            mid, w = render_weights([2.0], "neudf", r, n=20000, kind=kind)
            assert float(w[mid > 2.0 + 1e-3].sum()) < 1e-6
            offsets[kind, r] = front_offset(mid, w, 2.0)
    for r in (100.0, 400.0):
        assert offsets["exp", r] == pytest.approx(1.0 / (r * COS), rel=0.05)
        assert offsets["rational", r] > 4.0 * offsets["exp", r]
    assert offsets["rational", 400.0] < offsets["rational", 100.0] / 2  # a larger r shrinks it


def test_naive_neus_on_udf_puts_only_half_the_mass_on_the_first_surface():
    masses = [mass_near(*render_weights([1.5, 2.5], "neus_abs", s), 1.5) for s in (100.0, 1000.0, 1e4)]
    for m in masses:
        assert abs(m - 0.5) < 0.03, masses
    mid, w = render_weights([1.5, 2.5], "neus_abs", 1e4)
    assert mass_near(mid, w, 2.5) > 0.2  # the other half leaks behind: the bias the paper describes


def test_neus_on_a_signed_field_is_unbiased_for_a_closed_surface():
    # A solid slab between 1.5 and 2.5: SDF negative inside; NeuS stops at its front face.
    z = torch.linspace(0.0, 4.0, 2001, dtype=torch.float64)[None]
    dists = z[:, 1:] - z[:, :-1]
    mid = z[:, :-1] + dists / 2
    sdf = COS * torch.maximum(1.5 - mid, mid - 2.5)
    slope = torch.where(mid < 2.0, -COS, COS).to(torch.float64)
    prev, nxt = section_ends(sdf, slope, dists, 1.0, signed=True)
    w, _ = weights_from_alpha(alpha_for_mode("neus_sdf", prev, nxt, torch.tensor(1e4, dtype=torch.float64)))
    assert mass_near(mid[0], w[0], 1.5) > 0.95


@pytest.mark.parametrize("kind", ["rational", "exp", "atan"])
def test_varsigma_choices_follow_the_papers_rules(kind):
    d = torch.linspace(1e-3, 8.0, 4000, dtype=torch.float64, requires_grad=True)
    v = varsigma(d, 2.0, kind)
    (d1,) = torch.autograd.grad(v.sum(), d, create_graph=True)
    (d2,) = torch.autograd.grad(d1.sum(), d)
    assert float(varsigma(torch.zeros(1, dtype=torch.float64), 2.0, kind)) == 0.0
    assert abs(float(varsigma(torch.tensor([1e6], dtype=torch.float64), 2.0, kind)) - 1.0) < 1e-5
    assert bool((d1 > 0).all()) and bool((d2 < 0).all())


def test_unknown_varsigma_and_mode_are_rejected():
    with pytest.raises(ValueError, match="varsigma"):
        varsigma(torch.ones(1), 1.0, "tanh")
    with pytest.raises(ValueError, match="weight mode"):
        alpha_for_mode("volsdf", torch.ones(1), torch.ones(1), 1.0)


def test_importance_sampler_puts_most_new_samples_near_the_surface():
    torch.manual_seed(0)
    n_rays = 64
    rays_o = torch.zeros(n_rays, 3)
    rays_d = torch.tensor([[0.0, 0.0, 1.0]]).expand(n_rays, 3)
    depth = 1.0 + torch.rand(n_rays)  # a plane z = depth per ray, somewhere in [1, 2]
    z = torch.linspace(0.0, 3.0, 64).expand(n_rays, 64)

    def udf(points):
        return (points[:, 2].reshape(n_rays, -1) - depth[:, None]).abs().reshape(-1)

    out = hierarchical_samples(rays_o, rays_d, z, udf, n_importance=64, n_rounds=2, s0=64.0, deterministic=True)
    assert out.shape == (n_rays, 128)
    assert bool((out[:, 1:] >= out[:, :-1]).all())
    near = ((out - depth[:, None]).abs() < 0.1).float().sum(1) - ((z - depth[:, None]).abs() < 0.1).float().sum(1)
    assert float(near.mean()) > 0.8 * 64  # of the 64 new samples per ray, most land within 0.1 of the surface


def test_importance_weights_are_symmetric_about_the_surface():
    # zeta_s is even in the UDF, so the sampler does not favour either side (unlike the rendering weight).
    z = torch.linspace(0.0, 2.0, 401)[None]
    w = importance_weights(z, (z - 1.0).abs(), s=64.0)[0]
    mid = 0.5 * (z[0, 1:] + z[0, :-1])
    before = float(w[(mid > 0.9) & (mid < 1.0)].sum())
    after = float(w[(mid > 1.0) & (mid < 1.1)].sum())
    assert before > 0.2 and after > 0.1
    assert abs(float(w.sum()) - 1.0) < 1e-5


def test_regularised_normal_is_stable_across_the_cusp():
    # A ray crosses the plane z = 1 head on; the raw UDF gradient flips from -z to +z at the crossing.
    z = torch.linspace(0.5, 1.5, 40)  # no sample exactly on the plane
    points = torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], -1)[None]
    grads = torch.zeros_like(points)
    grads[..., 2] = torch.sign(z - 1.0)  # d|z-1|/dz
    normals = regularised_normals(points, grads, k_neighbours=5)[0]
    raw = grads[0]
    crossing = int((z > 1.0).nonzero()[0])
    just_after = slice(crossing, crossing + 2)
    assert bool((raw[just_after, 2] > 0).all()) and bool((raw[crossing - 2:crossing, 2] < 0).all())
    # The regularised normal keeps the approach side's direction for the samples right past the cusp.
    assert bool((normals[just_after, 2] < 0).all())
    # And it is a weighted mean of previous gradients: farther samples weigh more.
    i = crossing + 2
    w = torch.tensor([(points[0, i] - points[0, i - k]).pow(2).sum() for k in range(1, 6)])
    expected = (w[:, None] * raw[[i - k for k in range(1, 6)]]).sum(0) / w.sum()
    assert torch.allclose(normals[i], expected, atol=1e-6)
    assert torch.equal(normals[0], raw[0])  # the first sample has no history


def test_transmittance_telescopes_to_the_varsigma_ratio():
    # Approaching a surface, prod(1 - alpha) = varsigma(Psi(t)) / varsigma(Psi(t_0)) (supplement, Sec. C).
    mid, w = render_weights([3.0], "neudf", 5.0, n=400, t0=0.0, t1=2.0)
    psi_start, psi_end = COS * 3.0, COS * 1.0
    expected = float(varsigma(torch.tensor(psi_end), 5.0) / varsigma(torch.tensor(psi_start), 5.0))
    assert abs((1 - float(w.sum())) - expected) < 0.01


def test_a_ray_that_misses_a_surface_is_made_opaque_on_both_sides_of_its_closest_approach():
    # alpha = (max - min) / max absorbs while Psi falls and again while it rises, so a ray passing a
    # surface at distance d keeps varsigma(d)^2 of its light: a halo around silhouettes that is wide for
    # the rational varsigma at a small r (the reason for the r floor in `quick`).
    radius, t = 1.0, torch.linspace(-2.0, 2.0, 40001, dtype=torch.float64)[None]
    dists = t[:, 1:] - t[:, :-1]
    mid = t[:, :-1] + dists / 2
    opacity = {}
    for r, d in ((400.0, 0.01), (400.0, 0.002), (1600.0, 0.01)):
        impact = radius + d  # the ray x = (t, impact, 0) passes the sphere |x| = radius at distance d
        dist = torch.sqrt(mid**2 + impact**2)
        psi, slope = (dist - radius).abs(), mid / dist  # d|x|/dt along the ray
        prev, nxt = section_ends(psi, slope, dists, cos_anneal=1.0, signed=False)
        weights, _ = weights_from_alpha(alpha_for_mode("neudf", prev, nxt, torch.tensor(r, dtype=torch.float64)))
        expected = 1.0 - float(varsigma(torch.tensor(d), r)) ** 2
        assert float(weights.sum()) == pytest.approx(expected, rel=0.02), (r, d)
        opacity[r, d] = float(weights.sum())
    assert opacity[400.0, 0.01] == pytest.approx(0.36, abs=0.01)  # a miss by 0.01 at r = 400
    assert opacity[1600.0, 0.01] < 0.12  # a larger r narrows the halo


def test_without_receding_opacity_a_miss_keeps_varsigma_d_and_a_crossing_stays_opaque():
    r, radius = 400.0, 1.0
    t = torch.linspace(-2.0, 2.0, 40001, dtype=torch.float64)[None]
    dists = t[:, 1:] - t[:, :-1]
    mid = t[:, :-1] + dists / 2
    for d in (0.001, 0.003):
        impact = radius + d
        dist = torch.sqrt(mid**2 + impact**2)
        prev, nxt = section_ends((dist - radius).abs(), mid / dist, dists, cos_anneal=1.0, signed=False)
        alpha = alpha_for_mode("neudf", prev, nxt, torch.tensor(r, dtype=torch.float64), "exp", receding=False)
        weights, _ = weights_from_alpha(alpha)
        expected = 1.0 - float(varsigma(torch.tensor(d), r, "exp"))
        assert float(weights.sum()) == pytest.approx(expected, rel=0.02), d
    # half opaque at ln 2 / r from the silhouette, where the paper's two-sided alpha is 1.23 / r out
    assert 1.0 - float(varsigma(torch.tensor(math.log(2.0) / r), r, "exp")) == pytest.approx(0.5)

    # Crossing a plane with coarse or fine sections: the section that holds the zero has its mid-point
    # before it (falling: 50 sections) or past it (rising, kept for its clamped end: 20 and 2000).
    for n, shift in ((20, 0.13), (50, 0.031), (2000, 0.0017)):
        z = torch.linspace(shift, 4.0 + shift, n + 1, dtype=torch.float64)[None]
        dists = z[:, 1:] - z[:, :-1]
        psi, slope = plane_udf(z[:, :-1] + dists / 2, [2.0])
        prev, nxt = section_ends(psi, slope, dists, cos_anneal=1.0, signed=False)
        alpha = alpha_for_mode("neudf", prev, nxt, torch.tensor(r, dtype=torch.float64), "exp", receding=False)
        weights, transmittance = weights_from_alpha(alpha)
        assert float(transmittance) < 1e-4, (n, shift)


def test_receding_opacity_off_needs_gradient_sections():
    from pydantic import ValidationError

    from neudf_core.config import load_config

    assert not load_config("quick", {"renderer": {"receding_opacity": False}}).renderer.receding_opacity
    with pytest.raises(ValidationError, match="midpoint_gradient"):
        load_config("quick", {"renderer": {"receding_opacity": False, "section": "samples"}})


def test_zero_region_penalty_lifts_a_saturated_field_and_spares_a_surface():
    from neudf_core.losses import zero_region

    # Pre-activation values: deep in a flat zero region, at a surface crossing, and away from the surface.
    h = torch.tensor([-0.1, -0.06, -0.02, 0.0, 0.3], requires_grad=True)
    psi = torch.nn.functional.softplus(h, beta=100.0)
    valid = torch.ones_like(psi)
    grad_psi = torch.autograd.grad(psi.sum(), h, retain_graph=True)[0]
    assert grad_psi[0] < 1e-3  # what the eikonal term has to work with there: almost nothing
    loss = zero_region(h, valid, margin=0.03)
    assert float(loss.detach()) == pytest.approx((0.07 + 0.03) / 5, abs=1e-6)
    (grad,) = torch.autograd.grad(loss, h)
    assert torch.allclose(grad[:2], torch.full((2,), -0.2), atol=1e-6)  # pushes h up with full strength
    assert torch.all(grad[2:] == 0)  # a surface crossing (h > -margin) and the field away from it are left alone


def test_a_sheet_in_front_of_a_seen_point_is_in_its_line_of_sight_and_the_point_itself_is_not():
    """Psi = |z| (a sheet at z = 0). Seen from a camera at z = 2, a point behind the sheet (z = -0.3) has the
    sheet on its line of sight; a point on the sheet has nothing in front of it, and the line stops ``gap``
    short of it, so the sheet it lies on is not counted."""
    from neudf_core.losses import surface_in_sight
    from neudf_core.sampler import sight_lines

    torch.manual_seed(0)
    camera = torch.tensor([[0.0, 0.0, 2.0]]).expand(2, 3)
    points = torch.tensor([[0.1, 0.0, -0.3], [0.1, 0.0, 0.0]])
    lines, valid = sight_lines(points, camera, gap=0.03, n=400)
    assert valid.all()
    radius = lines.norm(dim=-1)
    assert radius.max() <= 1.0 + 1e-5  # only within the unit sphere, where the field is trained
    depth = (lines - camera[:, None]).norm(dim=-1)
    assert torch.all(depth <= (points - camera).norm(dim=-1)[:, None] - 0.03 + 1e-5)
    psi = lines[..., 2].abs().requires_grad_(True)
    per_line = torch.relu(0.01 - psi).sum(-1)
    assert per_line[0] > 0 and per_line[1] == 0
    loss = surface_in_sight(psi, valid, margin=0.01)
    assert float(loss.detach()) == pytest.approx(float(per_line.detach().sum()) / 2)
    (grad,) = torch.autograd.grad(loss, psi)
    assert grad[0].min() < 0 and torch.all(grad[1] == 0)  # it lifts Psi where the sheet is in the way
    # A point closer to the camera than the sphere's edge plus the gap has no stretch to check.
    _, none = sight_lines(torch.tensor([[0.0, 0.0, 1.01]]), camera[:1], gap=0.03, n=8)
    assert not none.any()
