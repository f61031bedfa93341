"""The mask figure: learned, empirical and true variance side by side on one colour scale, and a residual."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def mask_figure(
    learned: Tensor, empirical: Tensor, truth: Tensor | None = None, residual: Tensor | None = None, *, title: str = ""
):
    """A matplotlib figure of ``(H, W)`` variance maps (NaN = invalid, drawn black) and one pair's residual.

    The variance panels share one colour scale (grey levels squared) so they compare at a glance; the residual
    ``local - prior`` has its own diverging scale. Panels for ``truth`` and ``residual`` appear when given.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = {"learned": learned, "empirical (paper, 1/(n-1))": empirical}
    if truth is not None:
        maps["truth"] = truth
    arrays = {name: value.detach().double().cpu().numpy() for name, value in maps.items()}
    finite = np.concatenate([array[np.isfinite(array)] for array in arrays.values()])
    low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    panels = len(arrays) + (residual is not None)
    figure, axes = plt.subplots(1, panels, figsize=(3.3 * panels, 3.4), constrained_layout=True)
    axes = np.atleast_1d(axes)
    colours = plt.get_cmap("viridis").with_extremes(bad="black")
    for axis, (name, array) in zip(axes, arrays.items(), strict=False):
        image = axis.imshow(array, cmap=colours, vmin=low, vmax=high)
        axis.set_title(name, fontsize=9)
        axis.set_axis_off()
    figure.colorbar(image, ax=axes[: len(arrays)].tolist(), shrink=0.8, label="variance (grey levels²)")
    if residual is not None:
        values = residual.detach().double().cpu().numpy()
        spread = 3 * float(np.sqrt(np.nanmean(values**2))) if np.isfinite(values).any() else 1.0
        diverging = plt.get_cmap("RdBu_r").with_extremes(bad="black")
        image = axes[-1].imshow(values, cmap=diverging, vmin=-spread, vmax=spread)
        axes[-1].set_title("one residual, local - prior", fontsize=9)
        axes[-1].set_axis_off()
        figure.colorbar(image, ax=axes[-1], shrink=0.8, label="grey levels")
    if title:
        figure.suptitle(title, fontsize=10)
    return figure


def masked_residual(local: Tensor, prior: Tensor, valid: Tensor) -> Tensor:
    """``local - prior`` of one pair ``(1, H, W)`` as ``(H, W)`` float64, NaN where not valid."""
    return torch.where(valid[0], (local[0] - prior[0]).double(), torch.nan)
