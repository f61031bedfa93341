"""Time rectify / unrectify / PerspectiveVariance against bare kornia warp_perspective calls of the same sizes.

Usage:
    python -m data_tools.benchmarks.bench_rectify [--batch 8] [--repeats 15]

Prints the median wall time of each call over ``--repeats`` interleaved rounds (after one warm-up) and its ratio to
the bare ``warp_perspective`` call of the same output size in the same process, so the ratios stay meaningful on a
busy machine.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch
from kornia.geometry.transform import warp_perspective

from enmi_torch import GroundGrid, PerspectiveVariance, RoadCamera, rectify, unrectify
from enmi_torch.geometry.rectify import ground_to_image_homography


def median_ms(calls: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """Median milliseconds per call; the calls are interleaved round by round so that load spikes hit all alike."""
    for call in calls.values():
        call()
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    return {name: 1e3 * statistics.median(values) for name, values in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--cell", type=float, default=2.0, help="ground cell size in cm")
    args = parser.parse_args()

    torch.manual_seed(0)
    camera = RoadCamera.paper()
    grid = GroundGrid((-150.0, 150.0), (40.0, 200.0), args.cell)
    images = torch.rand(args.batch, 1, *camera.image_size) * 255
    birds_eye = torch.rand(args.batch, 1, *grid.shape) * 255
    image_to_grid = torch.linalg.inv(ground_to_image_homography(camera, grid)).float().expand(args.batch, 3, 3)
    model = PerspectiveVariance(camera, grid, 0.01)

    grid_to_image = ground_to_image_homography(camera, grid).float().expand(args.batch, 3, 3)
    to_grid, to_camera = "kornia warp_perspective to the grid", "kornia warp_perspective to the camera"
    calls = {
        to_grid: lambda: warp_perspective(images, image_to_grid, grid.shape),
        "rectify": lambda: rectify(images, camera, grid),
        "rectify, supersample=2": lambda: rectify(images, camera, grid, supersample=2),
        to_camera: lambda: warp_perspective(birds_eye, grid_to_image, camera.image_size),
        "unrectify": lambda: unrectify(birds_eye, camera, grid),
        "PerspectiveVariance forward": lambda: model(birds_eye),
        "PerspectiveVariance construction": lambda: PerspectiveVariance(camera, grid, 0.01),
    }
    reference_of = {"rectify": to_grid, "rectify, supersample=2": to_grid, "unrectify": to_camera}
    print(
        f"batch {args.batch}, camera {camera.image_size[0]}x{camera.image_size[1]}, grid {grid.shape[0]}x"
        f"{grid.shape[1]} ({args.cell:g} cm cells), torch {torch.__version__}, {torch.get_num_threads()} threads"
    )
    times = median_ms(calls, args.repeats)
    print("| call | median ms | ratio to the bare kornia warp of the same size |\n| --- | --- | --- |")
    for name, milliseconds in times.items():
        ratio = f"{milliseconds / times[reference_of[name]]:.2f}" if name in reference_of else ""
        print(f"| {name} | {milliseconds:.2f} | {ratio} |")


if __name__ == "__main__":
    main()
