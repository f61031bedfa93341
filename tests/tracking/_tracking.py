"""Helpers shared by the tracking tests: a smooth texture map, frames cut from it."""

from __future__ import annotations

import torch

from enmi_torch import Localization

FRAME = (24, 32)  # non-square frames: a swapped axis fails


def map_move(yaw: float, du: float, dv: float) -> tuple[float, float]:
    """The map move of an image-axes increment at ``yaw``, from Localization.local_to_map's linear part."""
    pose = torch.tensor([[0.0, 0.0, yaw]], dtype=torch.float64)
    transform = Localization(pose, *(torch.zeros(1),) * 5).local_to_map((5, 5))
    move = transform[0, :2, :2].double() @ torch.tensor([du, dv], dtype=torch.float64)
    return float(move[0]), float(move[1])


def texture(generator: torch.Generator, shape: tuple[int, int]) -> torch.Tensor:
    """A smooth random texture in grey levels: peaks a few cells wide, like a road surface."""
    noise = torch.rand(1, 1, *shape, generator=generator, dtype=torch.float64)
    smooth = torch.nn.functional.avg_pool2d(noise, 3, 1, 1, count_include_pad=False)
    return (smooth - smooth.min()) / (smooth.max() - smooth.min()) * 255


def cut(reference: torch.Tensor, x: int, y: int) -> torch.Tensor:
    """The frame whose centre pixel ``(h // 2, w // 2)`` lies on map cell ``(y, x)`` at yaw 0."""
    height, width = FRAME
    return reference[..., y - height // 2 : y - height // 2 + height, x - width // 2 : x - width // 2 + width]
