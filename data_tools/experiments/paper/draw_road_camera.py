"""Draw the paper's Fig. GridRoad for a camera config: tiled road, its camera image, the rectified view, the variance.

Usage:
    # writes runs/road_camera.png
    python -m data_tools.experiments.paper.draw_road_camera --config configs/camera/paper.yaml
    python -m data_tools.experiments.paper.draw_road_camera --figure docs/images/road_camera.png  # the README figure

The road is the config's grid of tiles with random shades N(128, 32^2) (the paper's simulation) and dark joints,
drawn on a grid twenty times finer; it is warped into the camera with ``unrectify``, back to the ground with
``rectify``, and the analytic variance ``N0 / A~`` of each tile is drawn on a log scale. Prints the numbers README
quotes.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
from matplotlib.colors import LogNorm

from enmi_torch import GroundGrid, PerspectiveVariance, RoadCamera, rectify, unrectify
from enmi_torch.geometry.camera import projected_area


def tiled_road(tiles: GroundGrid, refine: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Tile shades ``(H_t, W_t)`` and the road texture ``(1, 1, H_t * refine, W_t * refine)`` with joints."""
    shades = (128 + 32 * torch.randn(tiles.shape, generator=generator, dtype=torch.float64)).clamp(0, 255)
    texture = shades.repeat_interleave(refine, 0).repeat_interleave(refine, 1)
    joint = torch.zeros(refine, dtype=torch.bool)
    joint[0] = True
    joints = joint.repeat(tiles.shape[0])[:, None] | joint.repeat(tiles.shape[1])[None, :]
    return shades, torch.where(joints, 20.0, texture)[None, None]


def view_outline(camera: RoadCamera) -> tuple[list[float], list[float]]:
    """The visible road region's outline (a trapezoid) as lateral and distance coordinates."""
    near, far = camera.visible_distance_range()
    near_half, far_half = (float(camera.visible_half_width(d)) for d in (near, far))
    return [-near_half, near_half, far_half, -far_half, -near_half], [near, near, far, far, near]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("configs/camera/paper.yaml"))
    parser.add_argument("--figure", type=Path, default=Path("runs/road_camera.png"), help="PNG to write")
    parser.add_argument("--noise-power", type=float, default=0.01, help="N0 of the variance map")
    parser.add_argument("--refine", type=int, default=20, help="texture cells per tile side")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    camera, tiles = RoadCamera.from_yaml(args.config), GroundGrid.from_yaml(args.config)
    fine = tiles.refine(args.refine)
    shades, texture = tiled_road(tiles, args.refine, torch.Generator().manual_seed(args.seed))
    camera_image, on_road = unrectify(texture, camera, fine, mode="nearest")
    birds_eye, seen = rectify(camera_image, camera, fine, supersample=2)
    tile_centres, tiles_seen = rectify(camera_image, camera, tiles)
    model = PerspectiveVariance(camera, tiles, args.noise_power)
    captured = torch.zeros(1, 1, *tiles.shape, dtype=torch.float64)
    variance, valid = model(captured)[0, 0], model.valid_mask(captured)[0, 0]

    lateral, distance = tiles.lateral_edges(), tiles.distance_edges()
    whole = projected_area(camera, lateral[None, :-1], lateral[None, 1:], distance[1:, None], distance[:-1, None])
    interior = valid & torch.isclose(model.areas, whole, rtol=1e-12, atol=0)
    near, far = camera.visible_distance_range()
    rows = [
        ("visible road d (cm)", f"{near:.3f} to {far:.3f}"),
        ("tile grid (rows x columns)", f"{tiles.shape[0]} x {tiles.shape[1]}"),
        ("tiles seen (centre on the sensor), per row far to near", f"{valid.sum().item()}: {valid.sum(1).tolist()}"),
        ("A~ of whole tiles seen (cm^2)", f"{whole[interior].min():.3e} to {whole[interior].max():.3e}"),
        ("A~ of the seen part, partly seen tiles (cm^2)", f"{model.areas[valid & ~interior].min():.3e} and up"),
        (
            f"sigma^2 = N0 / A~ at N0 = {args.noise_power:g}",
            f"{variance[valid].min():.1f} to {variance[valid].max():.1f}",
        ),
        ("camera pixels on the tiled road", f"{on_road.double().mean():.4f}"),
        (
            "largest error of a rectified tile centre (0..255 scale)",
            f"{(tile_centres[0, 0] - shades)[tiles_seen[0, 0]].abs().max():.2e}",
        ),
    ]
    width = max(len(name) for name, _ in rows)
    print(f"| {'quantity'.ljust(width)} | value |\n| {'-' * width} | --- |")
    for name, value in rows:
        print(f"| {name.ljust(width)} | {value} |")

    (x_min, x_max), (d_near, d_far) = tiles.lateral_range, tiles.distance_range
    extent = (x_min, x_max, d_near, d_far)
    outline = view_outline(camera)
    gray = plt.get_cmap("gray").with_extremes(bad="#5b7fa3")
    figure, axes = plt.subplots(2, 2, figsize=(12, 7.6))
    axes = axes.flatten()
    axes[0].imshow(texture[0, 0].numpy(), cmap=gray, vmin=0, vmax=255, extent=extent)
    axes[0].plot(*outline, color="#e8a33d", lw=1.5)
    axes[0].set_title("tiled road (bird's-eye) and the camera's view")
    axes[1].imshow(np.ma.masked_where(~on_road[0, 0].numpy(), camera_image[0, 0].numpy()), cmap=gray, vmin=0, vmax=255)
    axes[1].set_title(f"camera image ({camera.image_size[0]} x {camera.image_size[1]} px)")
    axes[1].set_xlabel("u (px)")
    axes[1].set_ylabel("v (px)")
    axes[2].imshow(
        np.ma.masked_where(~seen[0, 0].numpy(), birds_eye[0, 0].numpy()), cmap=gray, vmin=0, vmax=255, extent=extent
    )
    axes[2].plot(*outline, color="#e8a33d", lw=1.0)
    axes[2].set_title("rectified from the camera image")
    shown = axes[3].imshow(
        np.ma.masked_where(~valid.numpy(), variance.numpy()),
        cmap=plt.get_cmap("viridis").with_extremes(bad="#d9d9d9"),
        norm=LogNorm(),
        extent=extent,
    )
    axes[3].plot(*outline, color="#e8a33d", lw=1.0)
    axes[3].set_title(f"variance N0 / A~ per tile, N0 = {args.noise_power:g}")
    figure.colorbar(shown, ax=axes[3], label="sigma^2 (log scale)", shrink=0.8)
    for axis in (axes[0], axes[2], axes[3]):
        axis.set_xlim(x_min, x_max)
        axis.set_ylim(d_near, d_far)
        axis.set_xlabel("lateral x (cm)")
        axis.set_ylabel("distance ahead d (cm)")
    figure.tight_layout()
    args.figure.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.figure, dpi=80)
    print(f"wrote {args.figure}")


if __name__ == "__main__":
    main()
