"""The localization figure: the share of held-out pairs each score and variance located, per held-out set."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from enmi_torch.training.held_out import METHOD_MEANINGS, held_out_order


def localization_figure(rates: Mapping[str, Mapping[str, float]], pairs: int, *, title: str = ""):
    """A table in colour: the share of held-out pairs each method (row) located in each held-out set (column).

    Shaped and lettered for TensorBoard's image card (about 400 x 215 pixels), like the mask figure.

    Args:
        rates: held-out set -> method -> share of the ``pairs`` held-out pairs located within one pixel.
        pairs: pairs per held-out set (the standard error of a share ``p`` is ``sqrt(p (1 - p) / pairs)``, at most
            ``0.5 / sqrt(pairs)``).
        title: the figure's title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from enmi_torch.training.mask_figure import FIGURE_SIZE, FONT

    sets = held_out_order(rates)
    methods = [method for method in METHOD_MEANINGS if any(method in rates[name] for name in sets)]
    methods += sorted({method for name in sets for method in rates[name]} - set(methods))
    shares = np.array([[rates[name].get(method, np.nan) for name in sets] for method in methods])
    figure, axis = plt.subplots(figsize=FIGURE_SIZE, layout="constrained")
    axis.imshow(shares, cmap="RdYlGn", vmin=0.0, vmax=1.0, aspect="auto")
    for (row, column), share in np.ndenumerate(shares):
        if np.isfinite(share):
            axis.text(column, row, f"{share:.2f}", ha="center", va="center", fontsize=FONT - 1)
    axis.set_xticks(range(len(sets)), [name.replace("_", " ") for name in sets], fontsize=FONT - 1)
    axis.xaxis.tick_top()
    axis.set_yticks(range(len(methods)), methods, fontsize=FONT - 2)
    axis.tick_params(length=0)
    stderr = 0.5 / max(pairs, 1) ** 0.5
    heading = f"share of {pairs} held-out pairs located (standard error at most {stderr:.2f})"
    figure.suptitle(f"{title}\n{heading}" if title else heading, fontsize=FONT - 3)
    return figure
