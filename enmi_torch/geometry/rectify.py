"""Bird's-eye rectification of road-camera images with kornia: the ground grid, its homography, warps both ways.

Convention:
    A :class:`GroundGrid` is a raster of square road cells, ``(H_g, W_g)``: row 0 is the *farthest* row (the bird's-eye
    image has "ahead" at the top, like the paper's mask figure), column 0 the leftmost. Grid pixel coordinates are
    ``(j, i)`` = (column, row) with cell centres at integers, so cell ``(i, j)`` is centred on the road point
    ``x = x_min + (j + 1/2) s``, ``d = d_far - (i + 1/2) s`` for cell size ``s``. Camera pixels follow
    :mod:`enmi_torch.geometry.camera`: ``(u, v)``, ``u`` right, ``v`` down, centres at integers.

    :func:`ground_to_image_homography` maps grid pixels ``(j, i, 1)`` to camera pixels ``(u, v, 1)``. kornia's
    ``warp_perspective(src, M, dsize)`` takes ``M`` mapping *source* pixels to *destination* pixels and samples the
    source at ``M^-1`` of each destination pixel; with ``align_corners=True`` (used throughout) its pixel centres
    are at integers, as here. So :func:`unrectify` passes the homography and :func:`rectify` its inverse.

    A cell is *seen* when its centre lies on the sensor (:func:`visible_cells`); samples there come from the nearest
    image data (``padding_mode="border"`` covers the half-pixel rim of the sensor) and everything unseen is set to 0.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from kornia.geometry.transform import warp_perspective
from torch import Tensor

from enmi_torch.geometry.camera import (
    RoadCamera,
    depth_from_focal_plane_y,
    focal_to_pixel_matrix,
    ground_to_focal_matrix,
    pixel_to_focal,
    pixel_to_ground,
    project_ground,
)
from enmi_torch.utils.budget import check_cells_memory
from enmi_torch.utils.checks import (
    check_floating,
    check_image_shape,
    check_option,
    check_positive_int,
    check_positive_number,
    check_value_range,
)
from enmi_torch.utils.config import check_config_keys, load_yaml_section

INTERPOLATIONS = ("bilinear", "nearest")


def _cell_count(name: str, extent: float, cell_size: float) -> int:
    count = extent / cell_size
    if round(count) < 1 or abs(count - round(count)) > 1e-6 * max(1.0, count):
        raise ValueError(f"{name} must span a whole number of cells of cell_size {cell_size}, got {count:g} cells")
    return round(count)


@dataclass(frozen=True)
class GroundGrid:
    """A bird's-eye raster of square road cells ahead of the camera.

    Args:
        lateral_range: ``(x_min, x_max)``, lateral extent (right positive), in the camera's length unit.
        distance_range: ``(d_near, d_far)``, distance ahead.
        cell_size: side ``s`` of a cell; both extents must be whole multiples of it.

    Convention:
        ``shape`` is ``(H_g, W_g)``; row 0 is the farthest row, column 0 the leftmost (see the module docstring).

    Example:
        >>> grid = GroundGrid((-150.0, 150.0), (40.0, 200.0), 20.0)  # the paper's 20 cm tiles
        >>> grid.shape
        (8, 15)
        >>> [c[0].item() for c in grid.cell_centers()]  # leftmost lateral centre, farthest distance centre
        [-140.0, 190.0]
    """

    lateral_range: tuple[float, float]
    distance_range: tuple[float, float]
    cell_size: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "lateral_range", check_value_range(self.lateral_range, "lateral_range"))
        object.__setattr__(self, "distance_range", check_value_range(self.distance_range, "distance_range"))
        object.__setattr__(self, "cell_size", check_positive_number("cell_size", self.cell_size))
        _cell_count("distance_range", self.distance_range[1] - self.distance_range[0], self.cell_size)
        _cell_count("lateral_range", self.lateral_range[1] - self.lateral_range[0], self.cell_size)

    @classmethod
    def from_dict(cls, config: Mapping[str, Any]) -> GroundGrid:
        """A grid from a mapping (a YAML section) with keys ``lateral_range``, ``distance_range``, ``cell_size``."""
        keys = ("lateral_range", "distance_range", "cell_size")
        check_config_keys("grid", config, required=keys)
        return cls(*(config[key] for key in keys))

    @classmethod
    def from_yaml(cls, path: str | Path, key: str = "grid") -> GroundGrid:
        """The grid in section ``key`` of a YAML file, e.g. ``configs/camera/paper.yaml``."""
        return cls.from_dict(load_yaml_section(path, key, "grid config file"))

    @property
    def shape(self) -> tuple[int, int]:
        """``(H_g, W_g)``: rows (distance) and columns (lateral)."""
        return (
            _cell_count("distance_range", self.distance_range[1] - self.distance_range[0], self.cell_size),
            _cell_count("lateral_range", self.lateral_range[1] - self.lateral_range[0], self.cell_size),
        )

    def refine(self, factor: int) -> GroundGrid:
        """The same extent with cells ``factor`` times smaller on each side (``factor x factor`` per cell)."""
        check_positive_int("factor", factor)
        return GroundGrid(self.lateral_range, self.distance_range, self.cell_size / factor)

    def lateral_edges(self, *, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
        """Lateral cell edges ``(W_g + 1,)``, left to right."""
        (low, high), cols = self.lateral_range, self.shape[1]
        return torch.linspace(low, high, cols + 1, dtype=dtype, device=device)

    def distance_edges(self, *, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
        """Distance cell edges ``(H_g + 1,)``, far to near (row 0's far edge first)."""
        (near, far), rows = self.distance_range, self.shape[0]
        return torch.linspace(far, near, rows + 1, dtype=dtype, device=device)

    def cell_centers(self, *, dtype: torch.dtype = torch.float64, device=None) -> tuple[Tensor, Tensor]:
        """Cell centres: lateral ``(W_g,)`` left to right and distance ``(H_g,)`` far to near."""
        lateral = self.lateral_edges(dtype=dtype, device=device)
        distance = self.distance_edges(dtype=dtype, device=device)
        return (lateral[:-1] + lateral[1:]) / 2, (distance[:-1] + distance[1:]) / 2

    def grid_to_ground_matrix(self, *, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
        """The ``3 x 3`` affine map from grid pixels ``(j, i, 1)`` to road points ``(x, d, 1)``."""
        s, x_min, d_far = self.cell_size, self.lateral_range[0], self.distance_range[1]
        rows = [[s, 0.0, x_min + s / 2], [0.0, -s, d_far - s / 2], [0.0, 0.0, 1.0]]
        return torch.tensor(rows, dtype=dtype, device=device)


def _check_grid(camera: Any, grid: Any) -> None:
    if not isinstance(camera, RoadCamera):
        raise TypeError(f"camera must be an enmi_torch.geometry.camera.RoadCamera, got {type(camera).__name__}")
    if not isinstance(grid, GroundGrid):
        raise TypeError(f"grid must be an enmi_torch.geometry.rectify.GroundGrid, got {type(grid).__name__}")
    behind = -camera.height * math.tan(camera.tilt)
    if grid.distance_range[0] <= behind:
        raise ValueError(
            f"grid distance_range must start in front of the camera (d > -h tan(theta) = {behind:.6g}), "
            f"got {grid.distance_range}"
        )


def ground_to_image_homography(
    camera: RoadCamera, grid: GroundGrid, *, dtype: torch.dtype = torch.float64, device=None
) -> Tensor:
    """The plane-induced homography ``(3, 3)`` from grid pixels ``(j, i, 1)`` to camera pixels ``(u, v, 1)``.

    ``H = K G A``: grid to road (:meth:`GroundGrid.grid_to_ground_matrix`), road to focal plane
    (:func:`~enmi_torch.geometry.camera.ground_to_focal_matrix`), focal plane to pixels
    (:func:`~enmi_torch.geometry.camera.focal_to_pixel_matrix`); scaled so that ``H[2, 2] = 1``.

    Convention:
        Built in float64 and cast to ``dtype``. This is the source-to-destination matrix that
        ``kornia.geometry.transform.warp_perspective`` takes to warp a bird's-eye image into the camera.

    Example:
        >>> camera, grid = RoadCamera.paper(), GroundGrid((-150.0, 150.0), (40.0, 200.0), 20.0)
        >>> homography = ground_to_image_homography(camera, grid)
        >>> from kornia.geometry.linalg import transform_points
        >>> nearest_middle_tile = torch.tensor([[[7.0, 7.0]]], dtype=torch.float64)  # (j, i): x = 0, d = 50
        >>> transform_points(homography[None], nearest_middle_tile).round(decimals=3)
        tensor([[[319.5000, 400.6830]]], dtype=torch.float64)
        >>> from enmi_torch.geometry.camera import ground_to_pixel
        >>> [round(c.item(), 3) for c in ground_to_pixel(camera, 0.0, 50.0)]  # the pinhole projection agrees
        [319.5, 400.683]
    """
    _check_grid(camera, grid)
    matrix = focal_to_pixel_matrix(camera) @ ground_to_focal_matrix(camera) @ grid.grid_to_ground_matrix()
    return (matrix / matrix[2, 2]).to(dtype=dtype, device=device)


def visible_cells(camera: RoadCamera, grid: GroundGrid, *, device=None) -> Tensor:
    """Bool ``(H_g, W_g)``: the cells whose centre the camera sees (it projects onto the sensor).

    Example:
        >>> visible_cells(RoadCamera.paper(), GroundGrid((-150.0, 150.0), (40.0, 200.0), 20.0)).sum(dim=1).tolist()
        [13, 13, 11, 9, 9, 7, 7, 5]
    """
    _check_grid(camera, grid)
    _check_grid_memory(grid, f"cell_size={grid.cell_size!r}", _MAP_BYTES, "the float64 maps")
    return _visible_cells(camera, grid).to(device, copy=True)


@functools.lru_cache(maxsize=32)
def _check_grid_memory(
    grid: GroundGrid, cause: str, bytes_per_cell: int, what: str, remedy: str = "raise cell_size"
) -> None:
    """Refuse maps over ``grid`` (``bytes_per_cell`` each cell) over the memory budget, before allocating them."""
    rows, cols = grid.shape
    what = f"{what} of the {rows} x {cols} ground grid"
    check_cells_memory(cause, rows * cols, bytes_per_cell, what, f"{remedy} or narrow the grid's ranges")


def _check_image_memory(camera: RoadCamera, bytes_per_pixel: int, what: str) -> None:
    """Refuse maps over the camera's pixels (``bytes_per_pixel`` each) over the memory budget, before allocating."""
    rows, cols = camera.image_size
    what = f"{what} of the {rows} x {cols} camera image"
    check_cells_memory(f"image_size={camera.image_size}", rows * cols, bytes_per_pixel, what, "lower image_size")


# visible_cells and pixels_on_grid: about four float64 maps (coordinates, projections) and the bool result.
_MAP_BYTES = 4 * 8 + 1


def _visible_cells(camera: RoadCamera, grid: GroundGrid) -> Tensor:
    lateral, distance = grid.cell_centers()
    focal_x, focal_y = project_ground(camera, lateral[None, :], distance[:, None])
    sensor_height, sensor_width = camera.sensor_size
    return (focal_x.abs() <= sensor_width / 2) & (focal_y.abs() <= sensor_height / 2)


def pixels_on_grid(camera: RoadCamera, grid: GroundGrid, *, device=None) -> Tensor:
    """Bool ``(H, W)``: the camera pixels whose road point lies on the grid (inside its outer cell edges)."""
    _check_grid(camera, grid)
    _check_image_memory(camera, _MAP_BYTES, "the float64 maps")
    return _pixels_on_grid(camera, grid).to(device, copy=True)


@functools.lru_cache(maxsize=32)
def _pixels_on_grid(camera: RoadCamera, grid: GroundGrid) -> Tensor:
    rows, cols = camera.image_size
    # A row of pixels sees one road distance; only the lateral position varies along it.
    u = torch.arange(cols, dtype=torch.float64)[None, :]
    v = torch.arange(rows, dtype=torch.float64)[:, None]
    depth = depth_from_focal_plane_y(camera, pixel_to_focal(camera, u[:, :1], v)[1])
    lateral, distance = pixel_to_ground(camera, u, v)
    (x_min, x_max), (d_near, d_far) = grid.lateral_range, grid.distance_range
    rows_inside = (depth > 0) & (distance >= d_near) & (distance <= d_far)
    return rows_inside & (lateral >= x_min) & (lateral <= x_max)


def _check_images(name: str, images: Tensor, size: tuple[int, int], size_name: str) -> None:
    check_floating(name, images)
    if images.ndim != 4 or tuple(images.shape[-2:]) != tuple(size):
        raise ValueError(
            f"{name} must have shape (B, C, {size[0]}, {size[1]}) ({size_name}), got {tuple(images.shape)}"
        )


def _batched(matrix: Tensor, like: Tensor) -> Tensor:
    return matrix.to(dtype=like.dtype, device=like.device).expand(like.shape[0], 3, 3)


def rectify(
    image: Tensor, camera: RoadCamera, grid: GroundGrid, *, mode: str = "bilinear", supersample: int = 1
) -> tuple[Tensor, Tensor]:
    """Warp camera images to the bird's-eye ground grid.

    Args:
        image: camera images ``(B, C, H, W)`` with ``(H, W) = camera.image_size``.
        camera: the road camera.
        grid: the ground grid.
        mode: ``"bilinear"`` or ``"nearest"`` sampling.
        supersample: ``k >= 1``; each cell becomes the mean of ``k x k`` samples on the cell (those the camera
            sees), the cell's mean amplitude that :class:`~enmi_torch.variance.PerspectiveVariance` describes.

    Returns:
        ``(birds_eye, valid)``: ``(B, C, H_g, W_g)`` in the dtype of ``image``, 0 where unseen, and the bool mask
        ``(1, 1, H_g, W_g)`` of the cells seen (:func:`visible_cells`; with ``supersample > 1`` also at least one
        sample seen).

    Convention:
        Grid row 0 is the farthest row. Differentiable in ``image``. Samples ``image`` at
        ``ground_to_image_homography(camera, grid)`` of each cell centre through kornia's ``warp_perspective``
        (``align_corners=True``, ``padding_mode="border"``).

    Example:
        >>> camera, grid = RoadCamera.paper((48, 64)), GroundGrid((-150.0, 150.0), (40.0, 200.0), 20.0)
        >>> birds_eye, valid = rectify(torch.rand(2, 3, 48, 64), camera, grid)
        >>> birds_eye.shape, valid.shape, int(valid.sum())
        (torch.Size([2, 3, 8, 15]), torch.Size([1, 1, 8, 15]), 74)
    """
    _check_images("image", image, camera.image_size, "camera.image_size")
    check_option("mode", mode, INTERPOLATIONS)
    check_positive_int("supersample", supersample)
    _check_grid(camera, grid)
    # Per fine cell: kornia's sampling grid (2 per image), the samples, their weighted copy, and the visibility maps.
    planes = 2 * image.shape[0] + 3 * image.shape[0] * image.shape[1]
    _check_grid_memory(
        grid,
        f"cell_size={grid.cell_size!r} with supersample={supersample}",
        supersample**2 * (planes * image.element_size() + _MAP_BYTES),
        f"the {supersample} x {supersample} samples per cell of {image.shape[0]} x {image.shape[1]} image plane(s)",
        "lower supersample, raise cell_size",
    )
    fine = grid.refine(supersample)
    image_to_grid = torch.linalg.inv(ground_to_image_homography(camera, fine))
    samples = warp_perspective(
        image, _batched(image_to_grid, image), fine.shape, mode=mode, padding_mode="border", align_corners=True
    )
    seen = visible_cells(camera, fine, device=image.device)
    if supersample == 1:
        return torch.where(seen, samples, 0.0), seen[None, None]
    weight = seen.to(image.dtype)[None, None]
    counts = F.avg_pool2d(weight, supersample)
    means = F.avg_pool2d(samples * weight, supersample) / counts.clamp_min(1 / supersample**2)
    valid = visible_cells(camera, grid, device=image.device)[None, None] & (counts > 0)
    return torch.where(valid, means, 0.0), valid


def unrectify(
    birds_eye: Tensor, camera: RoadCamera, grid: GroundGrid, *, mode: str = "bilinear"
) -> tuple[Tensor, Tensor]:
    """Warp bird's-eye images on the ground grid into the camera: the inverse of :func:`rectify`.

    Args:
        birds_eye: ``(B, C, H_g, W_g)`` on ``grid`` (row 0 farthest).
        camera: the road camera.
        grid: the ground grid.
        mode: ``"bilinear"`` or ``"nearest"`` sampling.

    Returns:
        ``(image, valid)``: ``(B, C, H, W)`` camera images, 0 off the grid, and the bool mask ``(1, 1, H, W)`` of the
        pixels whose road point lies on the grid (:func:`pixels_on_grid`).

    Convention:
        Differentiable in ``birds_eye``; kornia's ``warp_perspective`` with the source-to-destination matrix
        ``ground_to_image_homography(camera, grid)``, ``align_corners=True``, ``padding_mode="border"``.

    Example:
        >>> camera, grid = RoadCamera.paper((48, 64)), GroundGrid((-150.0, 150.0), (40.0, 200.0), 20.0)
        >>> image, valid = unrectify(torch.ones(1, 1, 8, 15), camera, grid)
        >>> image.shape, bool(valid.all()), image.sum().item() == valid.sum().item()
        (torch.Size([1, 1, 48, 64]), True, True)
    """
    _check_images("birds_eye", birds_eye, grid.shape, "grid.shape")
    check_option("mode", mode, INTERPOLATIONS)
    _check_grid(camera, grid)
    planes = 2 * birds_eye.shape[0] + 2 * birds_eye.shape[0] * birds_eye.shape[1]
    _check_image_memory(camera, planes * birds_eye.element_size() + _MAP_BYTES, "the sampled planes")
    homography = ground_to_image_homography(camera, grid)
    image = warp_perspective(
        birds_eye,
        _batched(homography, birds_eye),
        camera.image_size,
        mode=mode,
        padding_mode="border",
        align_corners=True,
    )
    valid = pixels_on_grid(camera, grid, device=birds_eye.device)[None, None]
    return torch.where(valid, image, 0.0), valid


def _check_homography(homography: Tensor) -> None:
    check_floating("homography", homography)
    if homography.ndim < 2 or tuple(homography.shape[-2:]) != (3, 3):
        raise ValueError(f"homography must have shape (..., 3, 3), got {tuple(homography.shape)}")


def homography_area_scale(homography: Tensor, points: Tensor) -> Tensor:
    """``|det J|`` of a homography at points: the local area scale from source to destination.

    For ``p -> (H p)_{1,2} / (H p)_3`` the Jacobian determinant is ``det(H) / w^3`` with ``w = (H p)_3``.

    Args:
        homography: ``(..., 3, 3)``, source to destination.
        points: source points ``(..., N, 2)`` as ``(x, y)``, batch dimensions broadcasting with ``homography``'s.

    Returns:
        ``(..., N)``: destination area per unit source area around each point.

    Convention:
        Differentiable in both arguments. Scale-free: ``c H`` gives the same result for any ``c != 0``.

    Example:
        >>> scale_by_three = torch.diag(torch.tensor([3.0, 3.0, 1.0]))
        >>> homography_area_scale(scale_by_three, torch.zeros(1, 2))
        tensor([9.])
    """
    _check_homography(homography)
    check_floating("points", points)
    if points.ndim < 2 or points.shape[-1] != 2:
        raise ValueError(f"points must have shape (..., N, 2), got {tuple(points.shape)}")
    last_row = homography[..., 2:, :]
    depth = points @ last_row[..., :2].transpose(-1, -2) + last_row[..., 2:]
    return (torch.linalg.det(homography).unsqueeze(-1) / depth.squeeze(-1) ** 3).abs()


def projected_cell_areas(homography: Tensor, shape: tuple[int, int]) -> Tensor:
    """Exact destination areas of the unit cells of a source raster under a homography.

    Cell ``(i, j)`` is the square ``[j - 1/2, j + 1/2] x [i - 1/2, i + 1/2]`` (pixel centres at integers); a
    homography maps it to a quadrilateral, whose area is the shoelace formula of its four projected corners.

    Args:
        homography: ``(..., 3, 3)``, source pixels to destination pixels.
        shape: ``(H, W)`` of the source raster.

    Returns:
        ``(..., H, W)`` areas in destination pixels squared.

    Raises:
        ValueError: if a cell corner maps to or beyond the line at infinity (``(H p)_3 <= 0``, e.g. a ground cell
            behind the camera).

    Example:
        >>> projected_cell_areas(torch.diag(torch.tensor([2.0, 3.0, 1.0])), (2, 2))
        tensor([[6., 6.],
                [6., 6.]])
    """
    _check_homography(homography)
    rows, cols = check_image_shape("shape", shape)
    ys, xs = torch.meshgrid(
        torch.arange(rows + 1, dtype=homography.dtype, device=homography.device) - 0.5,
        torch.arange(cols + 1, dtype=homography.dtype, device=homography.device) - 0.5,
        indexing="ij",
    )
    corners = torch.stack([xs, ys, torch.ones_like(xs)]).reshape(3, -1)
    projected = homography @ corners
    depth = projected[..., 2, :]
    if not torch.compiler.is_compiling() and bool((depth <= 0).any()):
        raise ValueError("homography must map every cell corner in front of the line at infinity ((H p)_3 > 0)")
    x, y = (projected[..., :2, :] / depth.unsqueeze(-2)).unflatten(-1, (rows + 1, cols + 1)).unbind(-3)
    # Shoelace over the corners (top-left, top-right, bottom-right, bottom-left) of every cell.
    quad_x = [x[..., :-1, :-1], x[..., :-1, 1:], x[..., 1:, 1:], x[..., 1:, :-1]]
    quad_y = [y[..., :-1, :-1], y[..., :-1, 1:], y[..., 1:, 1:], y[..., 1:, :-1]]
    twice_area = sum(quad_x[k] * quad_y[(k + 1) % 4] - quad_x[(k + 1) % 4] * quad_y[k] for k in range(4))
    return twice_area.abs() / 2
