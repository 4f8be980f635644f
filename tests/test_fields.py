"""The networks: Psi is non-negative and starts as a distance field; the hash grid and finite differences."""

import torch

from neudf_core.config import load_config
from neudf_core.fields import BackgroundNeRF, ColorNetwork, HashGridEncoding, UDFNetwork
from neudf_core.model import NeUDFModel, RenderState


def test_psi_is_non_negative_and_starts_as_the_distance_to_a_point():
    torch.manual_seed(0)
    net = UDFNetwork(init_radius=0.0)
    x = torch.randn(2000, 3) * 0.5
    psi, feature = net(x)
    assert bool((psi >= 0).all()) and feature.shape == (2000, 256)
    # Not exact (a random MLP smooths the cone's tip), but a field that grows away from one point with
    # a slope near 1, so no region starts flat.
    assert torch.corrcoef(torch.stack([psi, x.norm(dim=-1)]))[0, 1] > 0.9
    radii = torch.tensor([0.2, 0.4, 0.6, 0.8])
    direction = torch.nn.functional.normalize(torch.randn(200, 3), dim=-1)
    profile = torch.stack([net(direction * r)[0].mean() for r in radii])
    slopes = (profile[1:] - profile[:-1]) / 0.2
    assert bool((slopes > 0.5).all()) and bool((slopes < 1.5).all()), slopes


def test_abs_output_is_the_magnitude_of_the_same_field():
    torch.manual_seed(0)
    soft = UDFNetwork(d_hidden=64, n_layers=3, skip_in=(2,), init_radius=0.3)
    torch.manual_seed(0)
    absolute = UDFNetwork(d_hidden=64, n_layers=3, skip_in=(2,), init_radius=0.3, output="abs")
    x = torch.randn(500, 3) * 0.2  # inside the sphere of radius 0.3 the pre-activation is negative
    with torch.no_grad():
        psi_soft, raw, _ = soft.forward_with_raw(x)
        psi_abs, raw_abs, _ = absolute.forward_with_raw(x)
    assert torch.equal(raw, raw_abs) and bool((raw < 0).any()) and bool((raw > 0).any())
    assert torch.equal(psi_abs, raw.abs())
    assert torch.allclose(psi_soft, torch.nn.functional.softplus(raw, beta=100.0))
    # |h| reaches 0 where h does, with the slope of h; the Softplus stays above 0 and flattens instead
    crossing = raw.abs().argmin()
    assert float(psi_abs[crossing]) < float(psi_soft[crossing])


def test_colour_ignores_the_view_direction_only_when_told_to():
    torch.manual_seed(0)
    x, normals, features = torch.randn(100, 3), torch.randn(100, 3), torch.randn(100, 16)
    views_a = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1)
    views_b = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1)
    for view_dependent in (True, False):
        net = ColorNetwork(d_feature=16, d_hidden=32, n_layers=2, view_dependent=view_dependent)
        with torch.no_grad():
            differ = not torch.equal(net(x, views_a, normals, features), net(x, views_b, normals, features))
        assert differ == view_dependent


def test_background_colour_ignores_the_view_direction_only_when_told_to():
    torch.manual_seed(0)
    x = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1) * (1.0 + 5.0 * torch.rand(100, 1))
    views_a = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1)
    views_b = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1)
    for view_dependent in (True, False):
        net = BackgroundNeRF(d_hidden=32, n_layers=3, n_freqs=4, skip_in=(2,), view_dependent=view_dependent)
        with torch.no_grad():
            (sigma_a, rgb_a), (sigma_b, rgb_b) = net(x, views_a), net(x, views_b)
        assert torch.equal(sigma_a, sigma_b)
        assert (not torch.equal(rgb_a, rgb_b)) == view_dependent


def test_signed_network_starts_as_a_sphere_sdf():
    torch.manual_seed(0)
    net = UDFNetwork(init_radius=0.5, signed=True)
    inside, _ = net(torch.zeros(1, 3))
    outside, _ = net(torch.tensor([[0.9, 0.0, 0.0]]))
    assert float(inside.detach()) < 0 < float(outside.detach())


def test_hash_grid_is_continuous_and_uses_dense_and_hashed_levels():
    torch.manual_seed(0)
    enc = HashGridEncoding(n_levels=6, n_features=2, log2_table=12, base_res=4, max_res=64)
    assert bool(enc.dense[0]) and not bool(enc.dense[-1])
    with torch.no_grad():
        enc.table.uniform_(-1, 1)
    x = torch.rand(500, 3) * 1.8 - 0.9
    a, b = enc(x), enc(x + 1e-5)
    assert (a - b).abs().max() < 1e-2  # trilinear blending: no jumps between cells
    assert a.shape == (500, enc.d_out) and torch.equal(a[:, :3], x)


def test_finite_difference_gradient_matches_autograd():
    torch.manual_seed(0)
    cfg = load_config("fast")
    fd_model = NeUDFModel(cfg)
    exact_cfg = cfg.model_copy(deep=True)
    exact_cfg.field.gradient = "autograd"
    exact_model = NeUDFModel(exact_cfg)
    exact_model.load_state_dict(fd_model.state_dict())
    x = torch.rand(64, 3) - 0.5
    psi_fd, grad_fd, _ = fd_model.udf_and_grad(x)
    psi, grad, _ = exact_model.udf_and_grad(x)
    assert torch.allclose(psi_fd, psi)
    assert (grad_fd - grad).norm(dim=-1).max() < 0.05


def test_rays_that_reach_the_floor_inside_the_sphere_take_the_floors_colour():
    """With a floor plane, a ray going down onto the floor inside the unit sphere ends there in the floor
    texture's colour; rays that meet the floor beyond the sphere, go up, or start under it see the
    background as before."""
    torch.manual_seed(0)
    cfg = load_config("quick", {"background": {"floor": True}, "data": {"floor_y": -0.5}})
    model = NeUDFModel(cfg)
    eye = torch.tensor([0.0, 2.0, 2.5])
    targets = torch.tensor([[0.2, -0.5, 0.1],   # the floor inside the sphere
                            [1.5, -0.5, 0.0],   # the floor beyond it
                            [0.0, 3.0, 0.0]])   # up, away from the floor
    rays_o = torch.cat([eye.expand(3, 3), torch.tensor([[0.0, -0.9, 2.5]])])  # and an eye under the floor
    rays_d = torch.nn.functional.normalize(torch.cat([targets - eye, torch.tensor([[0.0, -0.2, -1.0]])]), dim=-1)
    background = torch.full((4, 3), 0.25)
    with torch.no_grad():
        out = model._floor_over_background(rays_o, rays_d, background)
        expected = model.floor(targets[:1, [0, 2]])
    assert torch.allclose(out[0], expected[0], atol=1e-5)
    assert torch.equal(out[1:], background[1:])

    state = RenderState(perturb=False)
    colours = []
    for bias in (-10.0, 10.0):  # a black floor, then a white one
        with torch.no_grad():
            model.floor.net[-1].bias.fill_(bias)
            colours.append(model.render(rays_o, rays_d, state)["color"])
    changed = (colours[1] - colours[0]).abs().amax(dim=-1)
    assert changed[0] > 0.05 and bool((changed[1:] == 0).all())
