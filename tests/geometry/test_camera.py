from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from _geometry import clip_to_box, pinhole_pixels, shoelace
from scipy import integrate

from enmi_torch.geometry.camera import (
    RoadCamera,
    camera_depth,
    depth_from_focal_plane_y,
    focal_plane_y,
    focal_to_pixel,
    ground_to_pixel,
    jacobian_determinant,
    pixel_to_focal,
    pixel_to_ground,
    project_ground,
    projected_area,
    signal_to_noise_ratio,
    tile_noise_variance,
    visible_projected_area,
)
from enmi_torch.geometry.rectify import GroundGrid

PAPER_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "camera" / "paper.yaml"
RECTANGLES = [  # (x_l, x_u, d_near, d_far): a paper tile, a wide slab, a thin strip far away, a tile off-axis
    (-10.0, 10.0, 40.0, 60.0),
    (-80.0, 30.0, 45.0, 170.0),
    (5.0, 5.5, 190.0, 199.0),
    (20.0, 40.0, 120.0, 140.0),
]


@pytest.fixture
def camera() -> RoadCamera:
    return RoadCamera.paper()


def test_visible_road_of_the_paper_camera(camera):
    near, far = camera.visible_distance_range()
    assert abs(near - 40.0) < 0.1
    assert abs(far - 200.0) < 0.1
    # The view's bottom and top rows meet the road there.
    assert float(focal_plane_y(camera, camera_depth(camera, near))) == pytest.approx(-camera.sensor_size[0] / 2)
    assert float(focal_plane_y(camera, camera_depth(camera, far))) == pytest.approx(camera.sensor_size[0] / 2)


def test_visible_half_width_is_the_sensor_edge(camera):
    distance = torch.linspace(40.0, 200.0, 9, dtype=torch.float64)
    focal_x, _ = project_ground(camera, camera.visible_half_width(distance), distance)
    torch.testing.assert_close(focal_x, torch.full_like(distance, camera.sensor_size[1] / 2))


@pytest.mark.parametrize("rectangle", RECTANGLES)
def test_projected_area_equals_integral_of_jacobian(camera, rectangle):
    x_l, x_u, d_near, d_far = rectangle
    z_l, z_u = float(camera_depth(camera, d_near)), float(camera_depth(camera, d_far))
    integral, _ = integrate.dblquad(
        lambda z, x: float(jacobian_determinant(camera, z)), x_l, x_u, z_l, z_u, epsabs=0, epsrel=1e-12
    )
    closed_form = float(projected_area(camera, x_l, x_u, d_near, d_far))
    assert closed_form == pytest.approx(integral, rel=1e-6)


@pytest.mark.parametrize("rectangle", RECTANGLES)
def test_projected_area_equals_shoelace_of_projected_corners(camera, rectangle, dtype):
    x_l, x_u, d_near, d_far = rectangle
    lateral = torch.tensor([x_l, x_u, x_u, x_l], dtype=torch.float64)
    distance = torch.tensor([d_near, d_near, d_far, d_far], dtype=torch.float64)
    corners = torch.stack(project_ground(camera, lateral, distance), dim=-1).numpy()
    bounds = [torch.tensor(b, dtype=dtype) for b in rectangle]
    closed_form = projected_area(camera, *bounds)
    assert closed_form.dtype == dtype
    assert float(closed_form) == pytest.approx(shoelace(corners), rel=1e-6 if dtype == torch.float64 else 1e-4)


def test_jacobian_determinant_matches_autograd(camera):
    def to_focal_plane(point):
        lateral, depth = point
        distance = (depth - camera.height * math.sin(camera.tilt)) / math.cos(camera.tilt)
        return torch.stack(project_ground(camera, lateral, distance))

    for lateral, depth in [(0.0, 70.0), (-30.0, 100.0), (55.0, 150.0)]:
        point = torch.tensor([lateral, depth], dtype=torch.float64)
        jacobian = torch.autograd.functional.jacobian(to_focal_plane, point)
        assert float(torch.linalg.det(jacobian)) == pytest.approx(float(jacobian_determinant(camera, depth)), rel=1e-9)


def test_projection_matches_a_rotated_pinhole(camera):
    generator = torch.Generator().manual_seed(0)
    distance = 30.0 + 200.0 * torch.rand(200, generator=generator, dtype=torch.float64)
    lateral = (torch.rand(200, generator=generator, dtype=torch.float64) - 0.5) * 2 * distance
    u, v = ground_to_pixel(camera, lateral, distance)
    u_ref, v_ref = pinhole_pixels(camera, lateral.numpy(), distance.numpy())
    np.testing.assert_allclose(u.numpy(), u_ref, atol=1e-6)
    np.testing.assert_allclose(v.numpy(), v_ref, atol=1e-6)


def test_pixel_convention_puts_the_sensor_corners_on_pixel_edges(camera):
    sensor_height, sensor_width = camera.sensor_size
    rows, cols = camera.image_size
    u, v = focal_to_pixel(
        camera,
        torch.tensor([-sensor_width / 2, sensor_width / 2]),
        torch.tensor([sensor_height / 2, -sensor_height / 2]),
    )
    torch.testing.assert_close(u, torch.tensor([-0.5, cols - 0.5]))
    torch.testing.assert_close(v, torch.tensor([-0.5, rows - 0.5]))


def test_round_trips(camera):
    depth = torch.linspace(60.0, 200.0, 15, dtype=torch.float64)
    torch.testing.assert_close(depth_from_focal_plane_y(camera, focal_plane_y(camera, depth)), depth)
    u = torch.tensor([0.0, 100.5, 639.0], dtype=torch.float64)
    v = torch.tensor([0.0, 240.0, 479.0], dtype=torch.float64)
    torch.testing.assert_close(torch.stack(focal_to_pixel(camera, *pixel_to_focal(camera, u, v))), torch.stack([u, v]))
    torch.testing.assert_close(
        torch.stack(ground_to_pixel(camera, *pixel_to_ground(camera, u, v))), torch.stack([u, v])
    )


def _clipped_shoelace(camera, x_l, x_u, d_near, d_far):
    """Exact visible focal-plane area: the projected rectangle (its edges are straight) clipped to the sensor."""
    lateral = np.array([x_l, x_u, x_u, x_l])
    distance = np.array([d_near, d_near, d_far, d_far])
    corners = np.stack([t.numpy() for t in project_ground(camera, torch.tensor(lateral), torch.tensor(distance))], -1)
    sensor_height, sensor_width = camera.sensor_size
    clipped = clip_to_box(corners, sensor_width / 2, sensor_height / 2)
    return shoelace(clipped) if len(clipped) else 0.0


@pytest.mark.parametrize(
    "rectangle",
    [
        (30.0, 50.0, 40.0, 60.0),  # a paper tile with a corner out of view
        (-200.0, 200.0, 20.0, 260.0),  # larger than the whole view
        (-150.0, -110.0, 160.0, 200.0),  # cut by the left edge
        (90.0, 150.0, 100.0, 210.0),  # cut by the right edge and the top
        (10.0, 30.0, 0.0, 45.0),  # cut by the bottom
        (-120.0, -100.0, 40.0, 60.0),  # out of view
        (-10.0, 10.0, 210.0, 230.0),  # beyond the top
    ],
)
def test_visible_projected_area_equals_clipped_polygon(camera, rectangle, dtype):
    reference = _clipped_shoelace(camera, *rectangle)
    area = visible_projected_area(camera, *(torch.tensor(b, dtype=dtype) for b in rectangle))
    assert area.dtype == dtype
    if reference == 0:
        assert float(area) == 0
    else:
        assert float(area) == pytest.approx(reference, rel=1e-9 if dtype == torch.float64 else 1e-4)


def test_visible_projected_area_is_projected_area_inside_the_view(camera):
    lateral = torch.arange(-40.0, 41.0, 20.0, dtype=torch.float64)
    distance = torch.arange(60.0, 181.0, 20.0, dtype=torch.float64)[:, None]
    inside = visible_projected_area(camera, lateral - 5, lateral + 5, distance, distance + 10)
    torch.testing.assert_close(inside, projected_area(camera, lateral - 5, lateral + 5, distance, distance + 10))


def test_areas_are_differentiable(camera):
    bounds = tuple(torch.tensor(b, dtype=torch.float64, requires_grad=True) for b in (25.0, 52.0, 41.0, 77.0))
    assert torch.autograd.gradcheck(lambda *b: visible_projected_area(camera, *b) * 1e5, bounds)
    assert torch.autograd.gradcheck(lambda *b: projected_area(camera, *b) * 1e5, bounds)


def test_snr_and_tile_variance_of_eq_snr(camera):
    near, far = torch.tensor([40.0, 180.0], dtype=torch.float64), torch.tensor([60.0, 200.0], dtype=torch.float64)
    area = projected_area(camera, -10.0, 10.0, near, far)
    snr = signal_to_noise_ratio(128.0, 0.01, area)
    variance = tile_noise_variance(0.01, area)
    torch.testing.assert_close(snr * variance, torch.full_like(area, 128.0**2))
    assert float(snr[0] / snr[1]) == pytest.approx(float(area[0] / area[1]))
    assert float(variance[1]) == pytest.approx(0.01 / 4.738052472627822e-06, rel=1e-6)


def test_sensor_size_and_fields_of_view_agree(camera):
    same = RoadCamera.from_sensor_size(camera.focal_length, camera.height, camera.tilt_deg, camera.sensor_size)
    assert same.vertical_fov_deg == pytest.approx(camera.vertical_fov_deg)
    assert same.horizontal_fov_deg == pytest.approx(camera.horizontal_fov_deg)
    pitch_y, pitch_x = camera.pixel_size
    assert (pitch_y * 480, pitch_x * 640) == pytest.approx(camera.sensor_size)


def test_paper_config_is_the_paper_camera(camera, tmp_path):
    assert RoadCamera.from_yaml(PAPER_CONFIG) == camera
    by_sensor = tmp_path / "sensor.yaml"
    by_sensor.write_text(
        "camera:\n  focal_length: 0.0367\n  height: 58.3095\n  tilt_deg: 35.9020\n"
        f"  sensor_size: [{camera.sensor_size[0]!r}, {camera.sensor_size[1]!r}]\n  image_size: [48, 64]\n"
    )
    loaded = RoadCamera.from_yaml(by_sensor)
    assert loaded.image_size == (48, 64)
    assert loaded.horizontal_fov_deg == pytest.approx(70.5)


PAPER = {
    "focal_length": 0.0367,
    "height": 58.3095,
    "tilt_deg": 35.902,
    "vertical_fov_deg": 39.3,
    "horizontal_fov_deg": 70.5,
}


@pytest.mark.parametrize(
    ("build", "error", "match"),
    [
        (lambda: RoadCamera(0.0, 1.0, 30.0, 20.0, 40.0), ValueError, "focal_length"),
        (lambda: RoadCamera(1.0, -1.0, 30.0, 20.0, 40.0), ValueError, "height"),
        (lambda: RoadCamera(1.0, 1.0, 95.0, 20.0, 40.0), ValueError, "tilt_deg"),
        (lambda: RoadCamera(1.0, 1.0, 30.0, 20.0, 190.0), ValueError, "horizontal_fov_deg"),
        (lambda: RoadCamera(1.0, 1.0, 10.0, 30.0, 40.0), ValueError, "half of vertical_fov_deg"),
        (lambda: RoadCamera(1.0, 1.0, 30.0, 20.0, 40.0, (48.5, 64)), ValueError, "image_size"),
        (lambda: RoadCamera(1.0, 1.0, 30.0, 20.0, 40.0, (48,)), ValueError, "image_size"),
        (lambda: RoadCamera("1", 1.0, 30.0, 20.0, 40.0), TypeError, "focal_length"),
        (lambda: RoadCamera.from_sensor_size(1.0, 1.0, 30.0, (0.5, -1.0)), ValueError, "sensor_size"),
        (lambda: RoadCamera.from_dict({**PAPER, "fov": 3}), ValueError, "unknown \\['fov'\\]"),
        (lambda: RoadCamera.from_dict({"height": 1.0}), ValueError, "missing \\['focal_length', 'tilt_deg'\\]"),
        (lambda: RoadCamera.from_dict({**PAPER, "sensor_size": [1, 1]}), ValueError, "not both"),
        (
            lambda: RoadCamera.from_dict({k: v for k, v in PAPER.items() if k != "vertical_fov_deg"}),
            ValueError,
            "missing",
        ),
        (lambda: RoadCamera.from_dict([1, 2]), TypeError, "mapping"),
        (lambda: RoadCamera.from_yaml(PAPER_CONFIG, key="lens"), ValueError, "no section 'lens'"),
        (lambda: RoadCamera.from_yaml(PAPER_CONFIG.with_name("missing.yaml")), FileNotFoundError, "does not exist"),
    ],
)
def test_invalid_inputs(build, error, match):
    with pytest.raises(error, match=match):
        build()


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"camera: [1, 2\n", r"is not readable YAML: expected ',' or '\]'.* at line 2, column 1"),
        (b"camera: !!python/object/apply:os.system ['echo hi']\n", r"tags such as !!python/\.\.\. are refused"),
        (b"\x80\xff\x00", "is not readable YAML: it is not UTF-8 text"),
        (b"[" * 100_000, "is not readable YAML: it nests too deeply"),
    ],
)
def test_from_yaml_refuses_a_malformed_file_naming_it(tmp_path, content, message):
    path = tmp_path / "camera.yaml"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=message) as raised:
        RoadCamera.from_yaml(path)
    assert f"camera config file {str(path)!r}" in str(raised.value)
    with pytest.raises(ValueError, match=message) as raised:  # the grid's loader reads the same files
        GroundGrid.from_yaml(path)
    assert f"grid config file {str(path)!r}" in str(raised.value)
