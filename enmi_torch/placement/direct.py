"""The reference for every surface: each placement scored on its own, as one aligned pair.

Slow (a Python loop over placements); :func:`~enmi_torch.scores.direct_surface` uses it to check the FFT surfaces on
small windows.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from enmi_torch.placement.inputs import Surface, SurfaceInputs
from enmi_torch.utils.checks import value_checks

# (sample, captured, section, variance or None, valid): the aligned pair at one placement, (1, 1, h, w) each.
PairScore = Callable[[int, Tensor, Tensor, "Tensor | None", Tensor], "Tensor | float"]


def direct_placements(inputs: SurfaceInputs, pair_score: PairScore, empty: float) -> Surface:
    """Every placement of every sample scored by ``pair_score``; ``empty`` where no valid pixel overlaps.

    Args:
        inputs: checked inputs (:func:`~enmi_torch.placement.inputs.check_inputs`).
        pair_score: the score of one aligned pair, called with the sample index and the ``(1, 1, h, w)`` captured
            image, reference section under it, captured variance (``None`` without one) and bool overlap mask.
        empty: the score of a placement without any valid overlapping pixel.

    Returns:
        :class:`~enmi_torch.placement.inputs.Surface` ``(B, Hw - h + 1, Ww - w + 1)``, without gradient.
    """
    batch, height, width = inputs.captured.shape
    rows = inputs.reference.shape[1] - height + 1
    cols = inputs.reference.shape[2] - width + 1
    score = inputs.captured.new_empty(batch, rows, cols)
    overlap = inputs.captured.new_empty(batch, rows, cols)
    # The inputs were checked as a whole; a small section under one placement may fall in one bin of the map's
    # range, which the value checks of an aligned call would refuse as a wrong value_range.
    with torch.no_grad(), value_checks(False):
        for sample in range(batch):
            window_index = sample if inputs.reference.shape[0] > 1 else 0
            captured = inputs.captured[sample][None, None]
            variance = None if inputs.variance is None else inputs.variance[sample][None, None]
            for row in range(rows):
                for col in range(cols):
                    cells = (window_index, slice(row, row + height), slice(col, col + width))
                    valid = inputs.captured_valid[sample] & inputs.reference_valid[cells]
                    count = int(valid.sum())
                    overlap[sample, row, col] = count
                    if count == 0:
                        score[sample, row, col] = empty
                        continue
                    section = inputs.reference[cells][None, None]
                    score[sample, row, col] = pair_score(sample, captured, section, variance, valid[None, None])
    return Surface(score, overlap)
