"""Local/prior image pairs: the on-disk format, synthetic pairs with a known noise field, and a Lightning module."""

from enmi_torch.data.datamodule import PairDataModule, ShardSampler
from enmi_torch.data.intensity import match_intensity
from enmi_torch.data.pairs import PairDataset, write_pairs
from enmi_torch.data.synthetic import KeptPairs, SyntheticPairs, gravel_texture, road_patch
from enmi_torch.data.truth import VarianceTruth, camera_truth, lidar_truth, make_truth

__all__ = [
    "KeptPairs",
    "PairDataModule",
    "PairDataset",
    "ShardSampler",
    "SyntheticPairs",
    "VarianceTruth",
    "camera_truth",
    "gravel_texture",
    "lidar_truth",
    "make_truth",
    "match_intensity",
    "road_patch",
    "write_pairs",
]
