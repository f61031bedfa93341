from __future__ import annotations

import pytest
import torch

from enmi_torch import ENMILoss
from enmi_torch.functional import enmi
from enmi_torch.geometry.camera import RoadCamera, camera_depth, projected_area, visible_projected_area
from enmi_torch.geometry.rectify import GroundGrid, ground_to_image_homography, visible_cells
from enmi_torch.variance import (
    PerspectiveVariance,
    VarianceModel,
    homography_variance,
    perspective_cell_areas,
    perspective_variance,
)

TILES = GroundGrid((-150.0, 150.0), (40.0, 200.0), 20.0)


@pytest.fixture
def camera() -> RoadCamera:
    return RoadCamera.paper()


def _cell_bounds(grid: GroundGrid):
    lateral, distance = grid.lateral_edges(), grid.distance_edges()
    return lateral[None, :-1], lateral[None, 1:], distance[1:, None], distance[:-1, None]


def test_module_agrees_with_function(camera, dtype, tolerance):
    model = PerspectiveVariance(camera, TILES, 0.02)
    assert isinstance(model, VarianceModel)
    captured = torch.zeros(3, 1, *TILES.shape, dtype=dtype)
    variance = model(captured)
    assert variance.shape == (1, 1, *TILES.shape) and variance.dtype == dtype
    torch.testing.assert_close(variance, perspective_variance(camera, TILES, 0.02, dtype=dtype), **tolerance)
    torch.testing.assert_close(variance, perspective_variance(camera, TILES, torch.tensor(0.02, dtype=dtype)))
    assert torch.equal(model.valid_mask(captured), visible_cells(camera, TILES)[None, None])


def test_variance_is_noise_power_over_the_exact_cell_area(camera):
    variance = perspective_variance(camera, TILES, 0.01)[0, 0]
    valid = visible_cells(camera, TILES)
    bounds = _cell_bounds(TILES)
    visible = visible_projected_area(camera, *bounds)
    whole = projected_area(camera, *bounds)
    torch.testing.assert_close(variance[valid], 0.01 / visible[valid], rtol=1e-12, atol=0)
    torch.testing.assert_close(variance[~valid], 0.01 / whole[~valid], rtol=1e-12, atol=0)
    fully_seen = torch.isclose(visible, whole, rtol=1e-12, atol=0)
    assert int((valid & ~fully_seen).sum()) > 0, "the paper grid has partly seen cells at the view's edges"
    # The middle column: whole tiles, 7.7e-5 cm^2 nearest to 4.7e-6 cm^2 farthest (paper, NOTES).
    middle = 0.01 / variance[:, 7]
    assert middle[-1].item() == pytest.approx(7.72e-5, rel=1e-3)
    assert middle[0].item() == pytest.approx(4.74e-6, rel=1e-3)


def test_positive_finite_and_masked_outside_the_view(camera):
    grid = GroundGrid((-250.0, 250.0), (10.0, 300.0), 5.0)
    model = PerspectiveVariance(camera, grid, 0.01)
    captured = torch.zeros(1, 1, *grid.shape, dtype=torch.float64)
    variance, valid = model(captured)[0, 0], model.valid_mask(captured)[0, 0]
    assert torch.isfinite(variance).all() and (variance > 0).all()
    lateral, distance = grid.cell_centers()
    near, far = camera.visible_distance_range()
    half_width = camera.visible_half_width(distance)[:, None]
    outside = (distance[:, None] < near) | (distance[:, None] > far) | (lateral[None, :].abs() > half_width)
    assert torch.equal(valid, ~outside)
    assert 0 < int(valid.sum()) < valid.numel()


def test_variance_grows_as_depth_cubed(camera):
    grid = GroundGrid((-20.0, 20.0), (40.0, 200.0), 1.0)
    variance = perspective_variance(camera, grid, 0.01)[0, 0]
    _, distance = grid.cell_centers()
    depth = camera_depth(camera, distance)[:, None].expand_as(variance)
    # Over a 1 cm cell the point Jacobian is exact to the cell's curvature: sigma^2 / z^3 = N0 / (f^2 h) per cm^2.
    ratio = variance / depth**3
    f, h = camera.focal_length, camera.height
    torch.testing.assert_close(ratio, torch.full_like(ratio, 0.01 / (f**2 * h)), rtol=1e-4, atol=0)
    slope = torch.diff(variance[:, 20].log()) / torch.diff(depth[:, 20].log())
    torch.testing.assert_close(slope, torch.full_like(slope, 3.0), rtol=1e-4, atol=0)


def test_homography_variance_agrees_on_whole_cells(camera, dtype):
    pitch_y, pitch_x = camera.pixel_size
    homography = ground_to_image_homography(camera, TILES, dtype=dtype)
    general = homography_variance(homography, TILES.shape, 0.01, pixel_area=pitch_y * pitch_x)
    assert general.shape == (1, 1, *TILES.shape) and general.dtype == dtype
    areas, _ = perspective_cell_areas(camera, TILES)
    whole = torch.isclose(areas, projected_area(camera, *_cell_bounds(TILES)), rtol=1e-12, atol=0)
    expected = perspective_variance(camera, TILES, 0.01, dtype=dtype)[0, 0]
    rtol = 1e-9 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(general[0, 0][whole], expected[whole], rtol=rtol, atol=0)
    batched = homography_variance(homography.expand(2, 3, 3), TILES.shape, 0.01, pixel_area=pitch_y * pitch_x)
    torch.testing.assert_close(batched, general.expand(2, 1, *TILES.shape))


def test_learnable_noise_power_gradcheck(camera):
    model = PerspectiveVariance(camera, TILES, 0.01, learnable=True).double()
    assert [name for name, _ in model.named_parameters()] == ["log_noise_power"]
    captured = torch.zeros(1, 1, *TILES.shape, dtype=torch.float64)

    def module_variance(log_noise_power):
        return torch.func.functional_call(model, {"log_noise_power": log_noise_power}, (captured,))

    log_noise_power = torch.tensor(0.01, dtype=torch.float64).log().requires_grad_()
    assert torch.autograd.gradcheck(module_variance, (log_noise_power,))
    noise_power = torch.tensor(0.01, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda n0: perspective_variance(camera, TILES, n0), (noise_power,))
    # d sigma^2 / d log N0 = sigma^2.
    (grad,) = torch.autograd.grad(model(captured).sum(), model.log_noise_power)
    torch.testing.assert_close(grad, model(captured).sum().detach())


def test_plugs_into_enmi_loss(camera):
    generator = torch.Generator().manual_seed(5)
    shape = (4, 1, *TILES.shape)
    reference = 128 + 32 * torch.randn(shape, generator=generator, dtype=torch.float64)
    model = PerspectiveVariance(camera, TILES, 0.01, learnable=True).double()
    noise = torch.randn(shape, generator=generator, dtype=torch.float64) * model(reference).detach().sqrt()
    captured = reference + noise
    loss = ENMILoss(variance_model=model, reduction="none")(captured, reference)
    valid = visible_cells(camera, TILES)
    direct = 2 - enmi(captured, reference, perspective_variance(camera, TILES, 0.01), valid_mask=valid)
    torch.testing.assert_close(loss, direct)
    loss.sum().backward()
    assert torch.isfinite(model.log_noise_power.grad) and model.log_noise_power.grad != 0


def test_state_dict_keeps_only_the_noise_power(camera):
    model = PerspectiveVariance(camera, TILES, 0.03)
    assert list(model.state_dict()) == ["log_noise_power"]
    restored = PerspectiveVariance(camera, TILES, 1.0)
    restored.load_state_dict(model.state_dict())
    assert restored.noise_power.item() == pytest.approx(0.03)
    assert "grid_shape=(8, 15)" in repr(model)


@pytest.mark.parametrize(
    ("build", "error", "match"),
    [
        (lambda: PerspectiveVariance(RoadCamera.paper(), TILES, 0.0), ValueError, "noise_power"),
        (lambda: PerspectiveVariance(RoadCamera.paper(), (8, 15), 0.01), TypeError, "GroundGrid"),
        (lambda: PerspectiveVariance(RoadCamera.paper(), TILES)(torch.zeros(1, 1, 8, 14)), ValueError, "8, 15"),
        (lambda: PerspectiveVariance(RoadCamera.paper(), TILES)(torch.zeros(1, 2, 8, 15)), ValueError, "captured"),
        (lambda: PerspectiveVariance(RoadCamera.paper(), TILES).valid_mask(torch.zeros(8, 15)), ValueError, "captured"),
        (lambda: PerspectiveVariance(RoadCamera.paper(), TILES)(torch.zeros(1, 1, 8, 15).long()), TypeError, "float"),
        (lambda: perspective_variance(RoadCamera.paper(), TILES, -1.0), ValueError, "noise_power"),
        (lambda: perspective_variance(RoadCamera.paper(), TILES, torch.tensor(-1.0)), ValueError, "noise_power"),
        (lambda: perspective_variance(RoadCamera.paper(), TILES, torch.ones(2)), ValueError, "0-d"),
        (lambda: homography_variance(torch.eye(3), (2, 2), 1.0, pixel_area=0.0), ValueError, "pixel_area"),
        (lambda: homography_variance(torch.eye(3)[None, None], (2, 2), 1.0), ValueError, "homography"),
        (lambda: homography_variance(torch.eye(3).long(), (2, 2), 1.0), TypeError, "homography"),
    ],
)
def test_invalid_inputs(build, error, match):
    with pytest.raises(error, match=match):
        build()


def test_runs_on_the_device_of_its_input(device, camera):
    model = PerspectiveVariance(camera, TILES, 0.01).to(device)
    captured = torch.zeros(1, 1, *TILES.shape, device=device)
    assert model(captured).device.type == device.type and model.valid_mask(captured).device.type == device.type
    noise_power = torch.tensor(0.01, dtype=torch.float64, device=device)
    torch.testing.assert_close(perspective_variance(camera, TILES, noise_power).cpu(), model(captured.double()).cpu())


def test_noise_power_is_a_fixed_positive_buffer_unless_learnable(camera):
    fixed = PerspectiveVariance(camera, TILES, 0.01)
    assert list(fixed.parameters()) == []
    assert len(list(PerspectiveVariance(camera, TILES, 0.01, learnable=True).parameters())) == 1
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match="noise_power must be a finite number > 0"):
            PerspectiveVariance(camera, TILES, bad)
        with pytest.raises(ValueError, match=rf"noise_power must be > 0, got {bad}"):
            perspective_variance(camera, TILES, torch.tensor(bad))
