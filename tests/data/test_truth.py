import math

import numpy as np
import pytest
import torch

from enmi_torch.data import VarianceTruth, camera_truth, lidar_truth, make_truth
from enmi_torch.geometry.camera import RoadCamera, project_ground


def test_lidar_truth_equals_loops():
    truth = lidar_truth((7, 9), 2.0, 5.0, range_fraction=0.8)
    sensor_range = 0.8 * min(6, 8) / 2
    for row in range(7):
        for col in range(9):
            radius = math.hypot(row - 3, col - 4)
            assert bool(truth.valid[row, col]) == (radius <= sensor_range)
            if radius <= sensor_range:
                expected = 4.0 + (25.0 - 4.0) * (radius / sensor_range) ** 2
                assert truth.variance[row, col].item() == pytest.approx(expected, rel=1e-12)
            else:
                assert math.isnan(truth.variance[row, col].item())


def numeric_cell_area(camera, left, right, near, far, steps=2000):
    """Focal-plane area of a ground cell by integrating |det J| dx dz = f^2 h sec(theta) / z^3 (midpoint rule)."""
    theta = camera.tilt
    distance = near + (np.arange(steps) + 0.5) * (far - near) / steps
    depth = distance * math.cos(theta) + camera.height * math.sin(theta)
    jacobian = camera.focal_length**2 * camera.height / math.cos(theta) / depth**3
    return (right - left) * float((jacobian * math.cos(theta)).sum() * (far - near) / steps)


def test_camera_truth_is_noise_power_over_integrated_area_and_view():
    camera = RoadCamera.paper()
    truth = camera_truth((6, 5), 2e-6, distance_range=(20.0, 230.0))
    distance_edges = np.linspace(230.0, 20.0, 7)
    lateral_edges = np.linspace(-87.5, 87.5, 6)  # square 35 cm cells, centred
    half_width, half_height = (
        camera.focal_length * math.tan(math.radians(camera.horizontal_fov_deg) / 2),
        camera.focal_length * math.tan(math.radians(camera.vertical_fov_deg) / 2),
    )

    def on_sensor(x, d):
        u, v = project_ground(camera, x, d)
        return abs(float(u)) <= half_width + 1e-12 and abs(float(v)) <= half_height + 1e-12

    for row in range(6):
        far, near = distance_edges[row], distance_edges[row + 1]
        for col in range(5):
            left, right = lateral_edges[col], lateral_edges[col + 1]
            assert bool(truth.valid[row, col]) == on_sensor((left + right) / 2, (near + far) / 2), (row, col)
            if all(on_sensor(x, d) for x in (left, right) for d in (near, far)):
                expected = 2e-6 / numeric_cell_area(camera, left, right, near, far)
                assert truth.variance[row, col].item() == pytest.approx(expected, rel=1e-6)
    assert truth.valid.any() and not truth.valid.all()


def test_camera_truth_grows_with_distance():
    truth = camera_truth((32, 32), 1e-5)
    column = truth.variance[:, 16][truth.valid[:, 16]]
    assert bool((column[:-1] > column[1:]).all())  # row 0 is the far edge


@pytest.mark.parametrize("flavour", ["lidar", "camera"])
def test_make_truth_sets_the_rms_noise(flavour):
    truth = make_truth(flavour, (40, 40), 7.0)
    assert math.sqrt(truth.mean_variance()) == pytest.approx(7.0, rel=1e-12)
    assert truth.flavour == flavour and truth.shape == (40, 40)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: make_truth("radar", (8, 8), 1.0), "flavour must be one of"),
        (lambda: make_truth("lidar", (8, 8), 0.0), "noise_std"),
        (lambda: lidar_truth((8, 8), range_fraction=1.5), "range_fraction"),
        (lambda: lidar_truth((8, -1)), "shape must be"),
        (lambda: camera_truth((8, 8), -1.0), "noise_power"),
        (lambda: camera_truth((8, 8), 1.0, distance_range=(5.0, -5.0)), "distance_range"),
        (lambda: camera_truth((8, 8), 1.0, distance_range=(-10.0, 50.0)), "ahead of the camera"),
        (lambda: VarianceTruth(torch.ones(3, 3), torch.ones(3, 3), "x"), "bool map"),
        (lambda: VarianceTruth(-torch.ones(3, 3), torch.ones(3, 3, dtype=torch.bool), "x"), "finite and > 0"),
        (lambda: lidar_truth((8, 8)).scaled(0.0), "factor"),
    ],
)
def test_invalid_inputs(make, match):
    with pytest.raises((ValueError, TypeError), match=match):
        make()
