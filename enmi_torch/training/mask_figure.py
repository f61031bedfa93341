"""The mask figure: learned, empirical and true variance side by side on one colour scale, and a residual."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

# TensorBoard shows an image card about 400 x 215 pixels: the figure is drawn for that shape, its text large enough
# to read there (14 pt on 6.4 inches shown 400 pixels wide is about 12 pixels).
FIGURE_SIZE = (6.4, 3.45)
FONT = 14


def mask_figure(
    learned: Tensor, empirical: Tensor, truth: Tensor | None = None, residual: Tensor | None = None, *, title: str = ""
):
    """A matplotlib figure of ``(H, W)`` variance maps (NaN = invalid, drawn black) and one pair's residual.

    The variance panels share one colour scale (grey levels squared) so they compare at a glance; the residual
    ``local - prior`` has its own diverging scale. Panels for ``truth`` and ``residual`` appear when given. One row,
    shaped and lettered for TensorBoard's image card.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = {"learned": learned, "empirical": empirical}
    if truth is not None:
        maps["truth"] = truth
    arrays = {name: value.detach().double().cpu().numpy() for name, value in maps.items()}
    finite = np.concatenate([array[np.isfinite(array)] for array in arrays.values()])
    low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    panels = len(arrays) + (residual is not None)
    figure, axes = plt.subplots(1, panels, figsize=FIGURE_SIZE, layout="constrained", squeeze=False)
    axes = axes[0]
    colours = plt.get_cmap("viridis").with_extremes(bad="black")
    for axis, (name, array) in zip(axes, arrays.items(), strict=False):
        image = axis.imshow(array, cmap=colours, vmin=low, vmax=high)
        axis.set_title(name, fontsize=FONT)
        axis.set_axis_off()
    bar = figure.colorbar(image, ax=axes[: len(arrays)].tolist(), shrink=0.7, location="bottom", aspect=30)
    bar.set_label("variance (grey levels²)", fontsize=FONT - 3)
    bar.ax.tick_params(labelsize=FONT - 4)
    if residual is not None:
        values = residual.detach().double().cpu().numpy()
        spread = 3 * float(np.sqrt(np.nanmean(values**2))) if np.isfinite(values).any() else 1.0
        diverging = plt.get_cmap("RdBu_r").with_extremes(bad="black")
        image = axes[-1].imshow(values, cmap=diverging, vmin=-spread, vmax=spread)
        axes[-1].set_title("a residual", fontsize=FONT)
        axes[-1].set_axis_off()
        bar = figure.colorbar(image, ax=axes[-1], shrink=0.7, location="bottom", aspect=10)
        bar.set_label("grey levels", fontsize=FONT - 3)
        bar.ax.tick_params(labelsize=FONT - 4)
    if title:
        figure.suptitle(title, fontsize=FONT - 2)
    return figure


def masked_residual(local: Tensor, prior: Tensor, valid: Tensor) -> Tensor:
    """``local - prior`` of one pair ``(1, H, W)`` as ``(H, W)`` float64, NaN where not valid."""
    return torch.where(valid[0], (local[0] - prior[0]).double(), torch.nan)
