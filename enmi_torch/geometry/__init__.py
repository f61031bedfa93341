"""The road camera and the bird's-eye ground grid: where a pixel's noise variance comes from (kornia warps)."""

from enmi_torch.geometry.camera import RoadCamera
from enmi_torch.geometry.rectify import GroundGrid, rectify, unrectify

__all__ = ["GroundGrid", "RoadCamera", "rectify", "unrectify"]
