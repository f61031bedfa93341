"""Per-pixel noise variance maps for ENMI: the interface and its implementations."""

from enmi_torch.variance.base import ConstantVariance, VarianceModel

__all__ = ["ConstantVariance", "VarianceModel"]
