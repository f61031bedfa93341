"""The score's likelihood scale and health threshold: :func:`calibrate_temperature` and the :class:`Calibration` file.

A score surface turns into a log-likelihood ``score * n_valid / temperature``; ECR is a Gaussian log-likelihood ratio
per pixel, so ``temperature = 1`` is its own scale, and :func:`calibrate_temperature` fits it on held-out frames for
any score. :class:`Calibration` saves it with the peak threshold next to a map.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch._checks import check_floating, check_option, check_positive_number
from enmi_torch.scores import score_names
from enmi_torch.tracking.belief import finite_floor


def calibrate_temperature(
    log_likelihoods: Tensor, truth: Tensor, *, bounds: tuple[float, float] = (1e-3, 1e4)
) -> float:
    """The temperature that makes ``softmax(log_likelihood / T)`` a calibrated posterior on held-out frames.

    Args:
        log_likelihoods: ``(N, Y, Sy, Sx)`` raw log-likelihoods (``score * n_valid``) of ``N`` held-out frames
            searched around their poses; ``-inf`` where a candidate was left out.
        truth: ``(N, 3)`` true ``(row, col, yaw)`` index of each frame on the grid (real numbers: the nearest bin
            counts).
        bounds: the search range of ``T``.

    Returns:
        ``T`` minimising the mean negative log probability of the true bin (a proper scoring rule), by golden
        section search over ``log T``.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> scale = 4.0  # a log-likelihood 4 times too sharp
        >>> truth = torch.randint(2, 7, (400, 2), generator=generator).double()
        >>> offsets = torch.randn(400, 2, generator=generator)  # the true peak's distance from the measured one
        >>> rows, cols = torch.meshgrid(torch.arange(9.0), torch.arange(9.0), indexing="ij")
        >>> peaks = truth + offsets
        >>> log_likelihood = -0.5 * scale * ((rows - peaks[:, :1, None]) ** 2 + (cols - peaks[:, 1:, None]) ** 2)
        >>> index = torch.cat([truth, torch.zeros(400, 1)], 1)[:, [0, 1, 2]]
        >>> 2.5 < calibrate_temperature(log_likelihood[:, None], index) < 6.5
        True
    """
    check_floating("log_likelihoods", log_likelihoods)
    check_floating("truth", truth)
    if log_likelihoods.ndim != 4 or truth.shape != (log_likelihoods.shape[0], 3):
        raise ValueError(
            "log_likelihoods must be (N, Y, Sy, Sx) and truth (N, 3), got "
            f"{tuple(log_likelihoods.shape)} and {tuple(truth.shape)}"
        )
    low, high = (check_positive_number("bounds", value) for value in bounds)
    yaw_count, rows, cols = log_likelihoods.shape[1:]
    index = truth.round().long()
    limits = torch.tensor([rows, cols, yaw_count], device=index.device)
    inside = ((index >= 0) & (index < limits[[0, 1, 2]])).all(1)
    if not bool(inside.any()):
        raise ValueError("truth must put at least one frame's true pose inside its grid, got none")
    values = finite_floor(log_likelihoods.double())[inside].flatten(1)
    index = index[inside]
    true_flat = (index[:, 2] * rows + index[:, 0]) * cols + index[:, 1]

    def loss(log_temperature: float) -> float:
        scaled = values / math.exp(log_temperature)
        return float((scaled.logsumexp(1) - scaled.gather(1, true_flat[:, None])[:, 0]).mean())

    left, right = math.log(low), math.log(high)
    ratio = (math.sqrt(5) - 1) / 2
    for _ in range(80):
        first, second = right - ratio * (right - left), left + ratio * (right - left)
        if loss(first) < loss(second):
            right = second
        else:
            left = first
    return math.exp((left + right) / 2)


class Calibration(NamedTuple):
    """The score's likelihood scale and health threshold, saved next to a map.

    Attributes:
        score: the name of the score they belong to (:func:`~enmi_torch.as_score`).
        temperature: divide ``score * n_valid`` by it to get a log-likelihood.
        min_peak_z: the smallest robust z-score of a surface's peak that counts as a match.
    """

    score: str
    temperature: float
    min_peak_z: float

    def save(self, path: str | Path) -> Path:
        """Write the calibration as JSON (e.g. ``map_calibration.json`` next to the map)."""
        path = Path(path)
        path.write_text(json.dumps(self._asdict(), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a calibration written by :meth:`save` (files that name the score ``metric`` too)."""
        values = json.loads(Path(path).read_text())
        if "metric" in values and "score" not in values:
            values["score"] = values.pop("metric")
        if set(values) != set(cls._fields):
            raise ValueError(f"{path}: a calibration needs keys {list(cls._fields)}, got {sorted(values)}")
        return cls(
            check_option("score", values["score"], score_names()),
            float(values["temperature"]),
            float(values["min_peak_z"]),
        )
