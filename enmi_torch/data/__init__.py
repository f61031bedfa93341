"""Local/prior image pairs: the on-disk format, synthetic pairs with a known noise field, and a Lightning module.

The example pair bundled with the library, two dates of Landsat 5 over Nanjing, is :func:`example_pair`.

:class:`PairDataModule` and :class:`ShardSampler` need Lightning (the ``train`` extra) and are imported on first use,
so that the rest of the package works with the core install.
"""

from typing import Any

from enmi_torch.data.example import ExamplePair, example_pair
from enmi_torch.data.intensity import match_intensity
from enmi_torch.data.pairs import PairDataset, write_pairs
from enmi_torch.data.synthetic import KeptPairs, SyntheticPairs, gravel_texture, road_patch
from enmi_torch.data.truth import VarianceTruth, camera_truth, lidar_truth, make_truth

__all__ = [
    "ExamplePair",
    "KeptPairs",
    "PairDataModule",
    "PairDataset",
    "ShardSampler",
    "SyntheticPairs",
    "VarianceTruth",
    "camera_truth",
    "example_pair",
    "gravel_texture",
    "lidar_truth",
    "make_truth",
    "match_intensity",
    "road_patch",
    "write_pairs",
]


def __getattr__(name: str) -> Any:
    """Import the Lightning data module only when it is asked for."""
    if name in ("PairDataModule", "ShardSampler"):
        from enmi_torch.data import datamodule

        return getattr(datamodule, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
