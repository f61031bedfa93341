"""GeoTransform: cells to world and back against rasterio's own arithmetic, and yaws against a frame carried by hand."""

import math

import numpy as np
import pytest
import torch
from _geotiffs import TRANSFORMS, WORLD_YAW, Affine, Window, rowcol, window_transform, xy

from enmi_torch.localization import Localization
from enmi_torch.maps import GeoTransform

SHEARED = Affine(0.5, 0.12, 300.0, -0.07, -0.8, 900.0)  # unequal cell sides and a shear: any invertible map


def _cells(count=50, seed=0):
    generator = np.random.default_rng(seed)
    return np.stack([generator.uniform(-20, 300, count), generator.uniform(-10, 200, count)], 1)


@pytest.mark.parametrize("name", [*TRANSFORMS, "sheared"])
def test_cells_go_to_the_world_as_rasterio_places_cell_centres_and_come_back(name):
    affine = TRANSFORMS.get(name, SHEARED)
    geo = GeoTransform.from_affine(affine)
    cells = _cells()
    world = geo.to_world(torch.from_numpy(cells)).numpy()
    # rasterio: transform * (col, row) is a pixel corner; the centre of cell (x, y) is half a cell in.
    expected = np.array([affine @ (x + 0.5, y + 0.5) for x, y in cells])
    np.testing.assert_allclose(world, expected, rtol=0, atol=1e-8)
    whole = np.floor(cells).astype(int)
    centres = np.stack(xy(affine, whole[:, 1], whole[:, 0], offset="center"), 1)  # rows, then columns
    np.testing.assert_allclose(geo.to_world(torch.from_numpy(whole.astype(float))).numpy(), centres, atol=1e-8)
    back = geo.to_cells(torch.from_numpy(world)).numpy()
    np.testing.assert_allclose(back, cells, rtol=0, atol=1e-8)
    rows, cols = rowcol(affine, centres[:, 0], centres[:, 1])  # the cell rasterio finds under each centre
    np.testing.assert_array_equal(np.stack([cols, rows], 1), whole)
    inverse = ~affine
    np.testing.assert_allclose(back, np.array([inverse @ (X, Y) for X, Y in world]) - 0.5, atol=1e-8)


def test_the_matrix_and_a_window_transform_agree_with_rasterio():
    affine = TRANSFORMS["rotated"]
    geo = GeoTransform.from_affine(affine)
    point = torch.tensor([12.0, 7.0, 1.0], dtype=torch.float64)
    assert torch.allclose(geo.matrix @ point, torch.tensor([*(affine @ (12.5, 7.5)), 1.0]).double(), atol=1e-9)
    window = geo.translated(40, -3)
    assert np.allclose(window.affine, tuple(window_transform(Window(40, -3, 10, 10), affine))[:6], atol=1e-9)
    assert torch.allclose(window.to_world((2.0, 5.0)), geo.to_world((42.0, 2.0)), atol=1e-9)
    assert GeoTransform.from_gdal(affine.to_gdal()) == geo
    assert geo.cell_size == pytest.approx((0.5, 0.5))
    assert GeoTransform.from_affine(SHEARED).cell_size == pytest.approx((math.hypot(0.5, 0.07), math.hypot(0.12, 0.8)))


def _heading_by_hand(affine: Affine, pose: tuple[float, float, float]) -> float:
    """World heading of the captured image's top: its pixels carried by the search's own frame, then by rasterio."""
    x, y, yaw = pose
    result = Localization(torch.tensor([[0.0, 0.0, yaw]], dtype=torch.float64), *(torch.zeros(1),) * 5)
    frame = result.local_to_map((round(y), round(x)), (9, 9))[0]  # captured pixel (x, y) -> map cell (x, y)
    centre, above = frame @ torch.tensor([4.0, 4.0, 1.0]).double(), frame @ torch.tensor([4.0, 3.0, 1.0]).double()
    start, end = affine @ (centre[0] + 0.5, centre[1] + 0.5), affine @ (above[0] + 0.5, above[1] + 0.5)
    return math.degrees(math.atan2(end[0] - start[0], end[1] - start[1]))


def _same_angle(first: float, second: float) -> bool:
    return abs((first - second + 180.0) % 360.0 - 180.0) < 1e-7


@pytest.mark.parametrize("name", [*TRANSFORMS, "sheared"])
@pytest.mark.parametrize("yaw", [0.0, 10.0, 90.0, -135.0, 179.0])
def test_a_yaw_becomes_the_heading_of_the_captured_image_s_top_in_the_world(name, yaw):
    affine = TRANSFORMS.get(name, SHEARED)
    geo = GeoTransform.from_affine(affine)
    world = geo.to_world((120.0, 80.0, yaw)).tolist()
    assert _same_angle(world[2], _heading_by_hand(affine, (120.0, 80.0, yaw)))
    if name in WORLD_YAW:  # the module docstring's closed forms
        assert _same_angle(world[2], WORLD_YAW[name](yaw))
    assert -180.0 < world[2] <= 180.0
    back = geo.to_cells(world).tolist()
    assert back[:2] == pytest.approx([120.0, 80.0], abs=1e-8) and _same_angle(back[2], yaw)


def test_north_up_heading_east_is_yaw_90_in_both_and_batches_keep_their_shape():
    geo = GeoTransform.from_affine(TRANSFORMS["north_up"])
    poses = torch.tensor([[[10.0, 20.0, 90.0], [0.0, 0.0, -180.0]]])  # (1, 2, 3)
    world = geo.to_world(poses)
    assert world.shape == (1, 2, 3) and world.dtype == torch.float64
    assert world[0, 0].tolist() == [500005.25, 5399989.75, 90.0] and world[0, 1, 2] == 180.0  # -180 wraps to 180
    assert geo.to_cells(world[..., :2]).shape == (1, 2, 2)


@pytest.mark.parametrize(
    ("call", "error", "message"),
    [
        (lambda: GeoTransform(1.0, 2.0, 0.0, 2.0, 4.0, 0.0), ValueError, "must be invertible"),
        (lambda: GeoTransform(1.0, 0.0, math.nan, 0.0, -1.0, 0.0), ValueError, "finite coefficients"),
        (lambda: GeoTransform(1.0, 0.0, "0", 0.0, -1.0, 0.0), TypeError, "six numbers"),
        (lambda: GeoTransform.from_affine((1.0, 0.0)), ValueError, "six numbers"),
        (lambda: GeoTransform.from_affine(TRANSFORMS["north_up"]).to_world((1.0,)), ValueError, r"shape \(\.\.\., 2\)"),
        (lambda: GeoTransform.from_affine(TRANSFORMS["north_up"]).to_cells((1.0, math.inf)), ValueError, "finite"),
        (lambda: GeoTransform.from_affine(TRANSFORMS["north_up"]).to_world("x"), TypeError, "numbers"),
    ],
)
def test_bad_transforms_and_poses_are_refused_by_name(call, error, message):
    with pytest.raises(error, match=message):
        call()
