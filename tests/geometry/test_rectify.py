from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from _geometry import pinhole_pixels
from kornia.geometry.linalg import transform_points
from kornia.geometry.transform import get_perspective_transform

from enmi_torch.geometry.camera import RoadCamera, ground_to_pixel, pixel_to_ground, projected_area
from enmi_torch.geometry.rectify import (
    GroundGrid,
    ground_to_image_homography,
    homography_area_scale,
    pixels_on_grid,
    projected_cell_areas,
    rectify,
    unrectify,
    visible_cells,
)
from enmi_torch.utils.budget import MemoryBudgetError

PAPER_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "camera" / "paper.yaml"
TILES = GroundGrid((-150.0, 150.0), (40.0, 200.0), 20.0)


@pytest.fixture
def small_camera() -> RoadCamera:
    return RoadCamera.paper((60, 80))


def _grid_points(grid: GroundGrid, count: int, generator: torch.Generator) -> torch.Tensor:
    """Random grid pixel coordinates ``(count, 2)`` as ``(j, i)`` over the whole grid, fractional."""
    rows, cols = grid.shape
    unit = torch.rand(count, 2, generator=generator, dtype=torch.float64)
    return unit * torch.tensor([cols, rows], dtype=torch.float64) - 0.5


def _ground_of(grid: GroundGrid, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    j, i = points.unbind(-1)
    return grid.lateral_range[0] + (j + 0.5) * grid.cell_size, grid.distance_range[1] - (i + 0.5) * grid.cell_size


def test_grid_layout():
    assert TILES.shape == (8, 15)
    lateral, distance = TILES.cell_centers()
    torch.testing.assert_close(lateral, torch.arange(-140.0, 141.0, 20.0, dtype=torch.float64))
    torch.testing.assert_close(distance, torch.arange(190.0, 49.0, -20.0, dtype=torch.float64))
    assert TILES.refine(4).shape == (32, 60)
    assert GroundGrid.from_yaml(PAPER_CONFIG) == TILES
    ground = transform_points(TILES.grid_to_ground_matrix()[None], torch.tensor([[[0.0, 0.0], [14.0, 7.0]]]).double())
    torch.testing.assert_close(ground[0], torch.tensor([[-140.0, 190.0], [140.0, 50.0]], dtype=torch.float64))


@pytest.mark.parametrize("camera", [RoadCamera.paper(), RoadCamera(0.5, 120.0, 20.0, 30.0, 50.0, (300, 500))])
def test_homography_maps_ground_points_like_the_pinhole(camera, generator):
    grid = GroundGrid((-200.0, 200.0), (40.0, 600.0), 8.0)
    points = _grid_points(grid, 500, generator)
    pixels = transform_points(ground_to_image_homography(camera, grid)[None], points[None])[0]
    u_ref, v_ref = pinhole_pixels(camera, *(t.numpy() for t in _ground_of(grid, points)))
    np.testing.assert_allclose(pixels.numpy(), np.stack([u_ref, v_ref], -1), atol=1e-4, rtol=0)


def test_homography_equals_four_point_transform():
    camera, grid = RoadCamera.paper(), TILES
    rows, cols = grid.shape
    corners = torch.tensor([[-0.5, -0.5], [cols - 0.5, -0.5], [cols - 0.5, rows - 0.5], [-0.5, rows - 0.5]]).double()
    pixels = torch.stack(ground_to_pixel(camera, *_ground_of(grid, corners)), dim=-1)
    four_point = get_perspective_transform(corners[None], pixels[None])[0]
    homography = ground_to_image_homography(camera, grid)
    torch.testing.assert_close(four_point / four_point[2, 2], homography, rtol=1e-7, atol=1e-9)


def test_visible_cells_are_the_cells_whose_centre_falls_on_the_sensor():
    camera, grid = RoadCamera.paper(), GroundGrid((-160.0, 160.0), (20.0, 240.0), 4.0)
    lateral, distance = grid.cell_centers()
    u, v = ground_to_pixel(camera, lateral[None, :], distance[:, None])
    rows, cols = camera.image_size
    expected = (u >= -0.5) & (u <= cols - 0.5) & (v >= -0.5) & (v <= rows - 0.5)
    seen = visible_cells(camera, grid)
    assert torch.equal(seen, expected)
    near, far = camera.visible_distance_range()
    assert not seen[distance > far + 2].any() and not seen[distance < near - 2].any()
    assert torch.equal(seen[:, lateral.abs() > 145], torch.zeros_like(seen[:, lateral.abs() > 145]))


def test_pixels_on_grid_are_the_pixels_whose_road_point_is_on_the_grid(small_camera):
    grid = GroundGrid((-60.0, 80.0), (60.0, 150.0), 10.0)
    on_grid = pixels_on_grid(small_camera, grid)
    rows, cols = small_camera.image_size
    v, u = torch.meshgrid(torch.arange(rows).double(), torch.arange(cols).double(), indexing="ij")
    lateral, distance = pixel_to_ground(small_camera, u, v)
    expected = (lateral >= -60) & (lateral <= 80) & (distance >= 60) & (distance <= 150)
    assert torch.equal(on_grid, expected)
    assert 0 < int(on_grid.sum()) < rows * cols


def test_rectify_samples_the_projected_cell_centres(small_camera, dtype, tolerance):
    rows, cols = small_camera.image_size
    grid = GroundGrid((-100.0, 100.0), (40.0, 200.0), 2.5)
    v, u = torch.meshgrid(torch.arange(rows, dtype=dtype), torch.arange(cols, dtype=dtype), indexing="ij")
    # Bilinear sampling reproduces affine images exactly, so each cell must read its own pixel position.
    image = torch.stack([u, v, 3 * u - 2 * v + 7])[None]
    birds_eye, valid = rectify(image, small_camera, grid)
    assert birds_eye.shape == (1, 3, *grid.shape) and birds_eye.dtype == dtype
    lateral, distance = grid.cell_centers()
    u_cell, v_cell = torch.broadcast_tensors(*ground_to_pixel(small_camera, lateral[None, :], distance[:, None]))
    interior = valid[0, 0] & (u_cell >= 0) & (u_cell <= cols - 1) & (v_cell >= 0) & (v_cell <= rows - 1)
    assert int(interior.sum()) > 0.9 * int(valid.sum())
    expected = torch.stack([u_cell, v_cell, 3 * u_cell - 2 * v_cell + 7]).to(dtype)
    atol = 2e-3 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(birds_eye[0][:, interior], expected[:, interior], rtol=0, atol=atol)
    assert torch.equal(birds_eye[0][:, ~valid[0, 0]], torch.zeros_like(birds_eye[0][:, ~valid[0, 0]]))


def test_unrectify_samples_the_road_points_of_the_pixels(small_camera, dtype):
    grid = GroundGrid((-120.0, 120.0), (40.0, 200.0), 4.0)
    rows, cols = grid.shape
    i, j = torch.meshgrid(torch.arange(rows, dtype=dtype), torch.arange(cols, dtype=dtype), indexing="ij")
    image, valid = unrectify(torch.stack([j, i])[None], small_camera, grid)
    height, width = small_camera.image_size
    v, u = torch.meshgrid(torch.arange(height).double(), torch.arange(width).double(), indexing="ij")
    lateral, distance = pixel_to_ground(small_camera, u, v)
    j_pixel = (lateral - grid.lateral_range[0]) / grid.cell_size - 0.5
    i_pixel = (grid.distance_range[1] - distance) / grid.cell_size - 0.5
    interior = valid[0, 0] & (j_pixel >= 0) & (j_pixel <= cols - 1) & (i_pixel >= 0) & (i_pixel <= rows - 1)
    assert int(interior.sum()) > 0.8 * height * width
    atol = 1e-3 if dtype == torch.float32 else 1e-9
    expected = torch.stack([j_pixel, i_pixel]).to(dtype)
    torch.testing.assert_close(image[0][:, interior], expected[:, interior], rtol=0, atol=atol)


def _smooth_image(camera: RoadCamera, dtype: torch.dtype) -> torch.Tensor:
    rows, cols = camera.image_size
    v, u = torch.meshgrid(torch.arange(rows, dtype=dtype), torch.arange(cols, dtype=dtype), indexing="ij")
    return (128 + 60 * torch.sin(2 * math.pi * u / cols) * torch.cos(math.pi * v / rows))[None, None]


def test_rectify_then_unrectify_returns_the_image(dtype):
    camera = RoadCamera.paper((120, 160))
    grid = GroundGrid((-150.0, 150.0), (36.0, 204.0), 0.5)
    image = _smooth_image(camera, dtype)
    birds_eye, _ = rectify(image, camera, grid)
    back, valid = unrectify(birds_eye, camera, grid)
    rows, cols = camera.image_size
    interior = valid[0, 0].clone()
    interior[:2], interior[-2:], interior[:, :2], interior[:, -2:] = False, False, False, False
    assert int(interior.sum()) > 0.9 * rows * cols
    error = (back - image)[0, 0][interior].abs().max()
    assert float(error) < 0.05  # on a 0..255 scale; the two bilinear resamplings of a smooth image


def _tile_texture(grid: GroundGrid, tile: float, shades: torch.Tensor) -> torch.Tensor:
    """Bird's-eye texture on ``grid``: square tiles of side ``tile`` (grid-aligned), one shade each."""
    lateral, distance = grid.cell_centers()
    column = ((lateral - grid.lateral_range[0]) // tile).long()
    row = ((grid.distance_range[1] - distance) // tile).long()
    return shades[row[:, None], column[None, :]][None, None]


@pytest.mark.parametrize("supersample", [1, 3])
def test_tiled_road_rendered_and_rectified_gives_back_the_tiles(dtype, generator, supersample):
    camera, tiles = RoadCamera.paper(), TILES
    shades = (128 + 32 * torch.randn(tiles.shape, generator=generator, dtype=torch.float64)).to(dtype)
    fine = tiles.refine(20)
    camera_image, on_grid = unrectify(_tile_texture(fine, tiles.cell_size, shades), camera, fine)
    assert on_grid.float().mean() > 0.9
    rectified, valid = rectify(camera_image, camera, tiles, supersample=supersample)
    assert torch.equal(valid[0, 0], visible_cells(camera, tiles))
    # Every sample (the centre, or the 3 x 3 sub-samples 6.7 cm apart) lies well inside its 20 cm tile.
    tolerance = 1e-3 if dtype == torch.float32 else 1e-9
    torch.testing.assert_close(rectified[0, 0][valid[0, 0]], shades[valid[0, 0]], rtol=0, atol=tolerance)
    assert torch.equal(rectified[0, 0][~valid[0, 0]], torch.zeros_like(shades[~valid[0, 0]]))


def test_rectify_is_batched_and_differentiable(small_camera):
    grid = GroundGrid((-100.0, 100.0), (40.0, 200.0), 20.0)
    generator = torch.Generator().manual_seed(3)
    images = torch.rand(3, 2, *small_camera.image_size, generator=generator, dtype=torch.float64)
    batched, _ = rectify(images, small_camera, grid, supersample=2)
    looped = torch.cat([rectify(images[k : k + 1], small_camera, grid, supersample=2)[0] for k in range(3)])
    torch.testing.assert_close(batched, looped)
    tiny = RoadCamera.paper((6, 8))
    image = torch.rand(1, 1, 6, 8, generator=generator, dtype=torch.float64, requires_grad=True)
    coarse = GroundGrid((-60.0, 60.0), (40.0, 200.0), 40.0)
    assert torch.autograd.gradcheck(lambda x: rectify(x, tiny, coarse)[0], (image,))
    birds_eye = torch.rand(1, 1, *coarse.shape, generator=generator, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: unrectify(x, tiny, coarse)[0], (birds_eye,))


def test_homography_area_scale_is_the_jacobian_determinant(generator):
    homography = torch.eye(3, dtype=torch.float64) + 0.2 * torch.randn(
        4, 3, 3, generator=generator, dtype=torch.float64
    )
    points = torch.rand(4, 5, 2, generator=generator, dtype=torch.float64)

    def mapped(point, matrix):
        return transform_points(matrix[None], point[None, None])[0, 0]

    for b in range(4):
        for n in range(5):
            jacobian = torch.autograd.functional.jacobian(lambda p, m=homography[b]: mapped(p, m), points[b, n])
            expected = torch.linalg.det(jacobian).abs()
            torch.testing.assert_close(homography_area_scale(homography, points)[b, n], expected)
    torch.testing.assert_close(
        homography_area_scale(-3 * homography, points), homography_area_scale(homography, points)
    )


def test_projected_cell_areas_are_the_camera_tile_areas():
    camera, grid = RoadCamera.paper(), TILES
    pitch_y, pitch_x = camera.pixel_size
    areas = projected_cell_areas(ground_to_image_homography(camera, grid), grid.shape) * pitch_y * pitch_x
    lateral, distance = grid.lateral_edges(), grid.distance_edges()
    expected = projected_area(camera, lateral[None, :-1], lateral[None, 1:], distance[1:, None], distance[:-1, None])
    torch.testing.assert_close(areas, expected, rtol=1e-9, atol=0)
    # The local area scale at the cell centre approximates the exact cell area (to the cell's curvature).
    rows, cols = grid.shape
    i, j = torch.meshgrid(torch.arange(rows).double(), torch.arange(cols).double(), indexing="ij")
    centres = torch.stack([j, i], dim=-1).reshape(-1, 2)
    point_scale = homography_area_scale(ground_to_image_homography(camera, grid), centres).reshape(rows, cols)
    torch.testing.assert_close(point_scale * pitch_y * pitch_x, expected, rtol=0.05, atol=0)


@pytest.mark.parametrize(
    ("build", "error", "match"),
    [
        (lambda: GroundGrid((10.0, -10.0), (40.0, 200.0), 20.0), ValueError, "lateral_range"),
        (lambda: GroundGrid((-10.0, 10.0), (40.0, float("inf")), 20.0), ValueError, "distance_range"),
        (lambda: GroundGrid((-10.0, 10.0), (40.0, 200.0), 0.0), ValueError, "cell_size"),
        (lambda: GroundGrid((-10.0, 10.0), (40.0, 205.0), 20.0), ValueError, "whole number of cells"),
        (lambda: GroundGrid("ab", (40.0, 200.0), 20.0), ValueError, "lateral_range"),
        (lambda: GroundGrid.from_dict({"lateral_range": [-1, 1], "cell_size": 1}), ValueError, "distance_range"),
        (lambda: TILES.refine(0), ValueError, "factor"),
        (lambda: visible_cells(RoadCamera.paper(), GroundGrid((-1.0, 1.0), (-90.0, 10.0), 1.0)), ValueError, "front"),
        (lambda: visible_cells("camera", TILES), TypeError, "RoadCamera"),
        (lambda: ground_to_image_homography(RoadCamera.paper(), (8, 15)), TypeError, "GroundGrid"),
        (lambda: rectify(torch.zeros(1, 1, 48, 64), RoadCamera.paper(), TILES), ValueError, "480, 640"),
        (
            lambda: rectify(torch.zeros(1, 1, 480, 640, dtype=torch.long), RoadCamera.paper(), TILES),
            TypeError,
            "floating",
        ),
        (lambda: rectify(torch.zeros(1, 1, 480, 640), RoadCamera.paper(), TILES, mode="bicubic"), ValueError, "mode"),
        (
            lambda: rectify(torch.zeros(1, 1, 480, 640), RoadCamera.paper(), TILES, supersample=0),
            ValueError,
            "supersample",
        ),
        (lambda: unrectify(torch.zeros(1, 8, 15), RoadCamera.paper(), TILES), ValueError, "birds_eye"),
        (lambda: homography_area_scale(torch.eye(2), torch.zeros(1, 2)), ValueError, "homography"),
        (lambda: homography_area_scale(torch.eye(3), torch.zeros(1, 3)), ValueError, "points"),
        (lambda: projected_cell_areas(torch.eye(3), (0, 2)), ValueError, "shape"),
        (
            lambda: projected_cell_areas(torch.tensor([[1.0, 0, 0], [0, 1, 0], [1, 0, 0]]), (2, 2)),
            ValueError,
            "infinity",
        ),
    ],
)
def test_invalid_inputs(build, error, match):
    with pytest.raises(error, match=match):
        build()


def test_runs_on_the_device_of_its_input(device, small_camera):
    grid = GroundGrid((-100.0, 100.0), (40.0, 200.0), 5.0)
    generator = torch.Generator().manual_seed(4)
    images = torch.rand(2, 1, *small_camera.image_size, generator=generator)
    birds_eye, valid = rectify(images.to(device), small_camera, grid, supersample=2)
    assert birds_eye.device.type == device.type and valid.device.type == device.type
    torch.testing.assert_close(birds_eye.cpu(), rectify(images, small_camera, grid, supersample=2)[0])
    back, on_grid = unrectify(birds_eye, small_camera, grid)
    assert back.device.type == device.type and on_grid.device.type == device.type


FINE_GRID = GroundGrid((-150.0, 150.0), (40.0, 200.0), 0.001)  # 160000 x 300000 cells


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (
            lambda camera, grid: rectify(torch.rand(1, 1, 48, 64), camera, grid, supersample=100_000),
            r"cell_size=20.0 with supersample=100000 needs about .* TiB.*: lower supersample",
        ),
        (
            lambda camera, grid: rectify(
                torch.rand(1, 1, 48, 64), camera, GroundGrid((-150.0, 150.0), (40.0, 200.0), 0.001)
            ),
            r"cell_size=0.001 with supersample=1 needs about .* of the 160000 x 300000 ground grid",
        ),
        (
            lambda camera, grid: visible_cells(camera, FINE_GRID),
            r"cell_size=0.001 needs about 1.4 TiB for the float64 maps of the 160000 x 300000 ground grid",
        ),
        (
            lambda camera, grid: pixels_on_grid(RoadCamera.paper((100_000, 100_000)), grid),
            r"image_size=\(100000, 100000\) needs about .* GiB for the float64 maps of the 100000 x 100000 camera",
        ),
        (
            lambda camera, grid: unrectify(torch.ones(1, 1, 8, 15), RoadCamera.paper((100_000, 100_000)), grid),
            r"image_size=\(100000, 100000\) needs about .* GiB for the sampled planes",
        ),
    ],
)
def test_sizes_over_the_memory_budget_are_refused_before_allocating(call, message):
    camera, grid = RoadCamera.paper((48, 64)), GroundGrid((-150.0, 150.0), (40.0, 200.0), 20.0)
    with pytest.raises(MemoryBudgetError, match=message):
        call(camera, grid)
