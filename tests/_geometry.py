"""Independent references for the camera tests: a 3-D pinhole with an explicit rotation, polygon clipping."""

from __future__ import annotations

import math

import numpy as np

from enmi_torch.geometry.camera import RoadCamera


def pinhole_pixels(camera: RoadCamera, lateral: np.ndarray, distance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of road points from a world-to-camera rotation, not from the paper's closed forms.

    World: X right, Y up, Z ahead (horizontal), road at Y = 0, pinhole at (0, h, 0). The camera pitches down by
    theta about X; its axes are X right, Y' up in the image, Z' along the optical axis.
    """
    theta = camera.tilt
    rotation = np.array(
        [[1.0, 0.0, 0.0], [0.0, math.cos(theta), math.sin(theta)], [0.0, -math.sin(theta), math.cos(theta)]]
    )
    points = np.stack([lateral, np.zeros_like(lateral) - camera.height, distance], axis=-1)
    x_cam, y_cam, z_cam = np.moveaxis(points @ rotation.T, -1, 0)
    focal_x, focal_y = camera.focal_length * x_cam / z_cam, camera.focal_length * y_cam / z_cam
    (sensor_height, sensor_width), (rows, cols) = camera.sensor_size, camera.image_size
    u = (focal_x + sensor_width / 2) / (sensor_width / cols) - 0.5
    v = (sensor_height / 2 - focal_y) / (sensor_height / rows) - 0.5
    return u, v


def shoelace(polygon: np.ndarray) -> float:
    """Area of a simple polygon ``(N, 2)``."""
    x, y = polygon[:, 0], polygon[:, 1]
    return abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))) / 2


def clip_to_box(polygon: np.ndarray, half_width: float, half_height: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon ``(N, 2)`` to ``|x| <= half_width``, ``|y| <= half_height``."""
    edges = [(0, -1.0, half_width), (0, 1.0, half_width), (1, -1.0, half_height), (1, 1.0, half_height)]
    points = [tuple(p) for p in polygon]
    for axis, sign, bound in edges:
        kept = []
        for k, current in enumerate(points):
            previous = points[k - 1]
            inside_current = sign * current[axis] <= bound
            inside_previous = sign * previous[axis] <= bound
            if inside_current != inside_previous:
                t = (bound - sign * previous[axis]) / (sign * current[axis] - sign * previous[axis])
                kept.append(tuple(previous[i] + t * (current[i] - previous[i]) for i in range(2)))
            if inside_current:
                kept.append(current)
        points = kept
        if not points:
            return np.zeros((0, 2))
    return np.array(points)
