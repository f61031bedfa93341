"""The score's likelihood scale and health threshold: the grid temperature, a fitted one, the calibration file.

A score surface turns into a log-likelihood ``score * n_valid / temperature``. ECR is a Gaussian log-likelihood ratio
per pixel, but its peak can be far narrower than the filter's bins (thousands of nats lost one cell from the peak):
the belief cannot hold a likelihood sharper than its own bins, and the sub-cell position and yaw are unknown within
them. :func:`grid_temperature`, the tracker's default, flattens each frame's log-likelihood just enough that no axis
is sharper than a pose spread uniformly over one bin (variance ``width^2 / 12``); nothing is fitted.
:func:`calibrate_temperature` fits one temperature on surveyed frames instead, for any score. :class:`Calibration`
saves it with the peak threshold and the noise model it was fitted with next to a map.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.scores import score_names
from enmi_torch.tracking.belief import finite_floor
from enmi_torch.tracking.settings import NOISE_MODELS
from enmi_torch.utils.checks import check_floating, check_positive_number
from enmi_torch.utils.files import describe_json, read_json


def grid_temperature(log_likelihood: Tensor) -> Tensor:
    """The temperature that makes a log-likelihood on the filter's grid no sharper than one bin, per sample.

    At the peak of each sample's ``(Y, Sy, Sx)`` log-likelihood (the argmax, moved one bin inwards at a border), the
    curvature along each axis of length >= 3 is the negative second difference ``h`` in bins^-2. A Gaussian with that
    curvature has variance ``1 / h`` bins^2; add the variance ``1 / 12`` of a pose uniform within its bin (what the grid
    cannot resolve) and the curvature becomes ``h / (1 + h / 12)``. The temperature is ``1 + max(h) / 12`` over the
    axes: the sharpest axis gets exactly that, the others at most it. A flat or dipped axis counts ``h = 0``, so a
    likelihood no sharper than its bins keeps its scale (temperature 1).

    Args:
        log_likelihood: ``(B, Y, Sy, Sx)`` log-likelihoods (``score * n_valid``); non-finite values are read as the
            sample's smallest finite one.

    Returns:
        ``(B,)`` float64 temperatures ``>= 1``.

    Example:
        >>> rows, cols = torch.meshgrid(torch.arange(-3.0, 4.0), torch.arange(-3.0, 4.0), indexing="ij")
        >>> sharp = -0.5 * (120.0 * cols**2 + 24.0 * rows**2)  # curvatures 120 and 24 per bin^2
        >>> grid_temperature(sharp[None, None]).tolist()  # 1 + 120 / 12
        [11.0]
    """
    check_floating("log_likelihood", log_likelihood)
    if log_likelihood.ndim != 4:
        raise ValueError(f"log_likelihood must be (B, Y, Sy, Sx), got {tuple(log_likelihood.shape)}")
    values = finite_floor(log_likelihood.double())
    batch, *sizes = values.shape
    index = torch.stack(torch.unravel_index(values.flatten(1).argmax(1), sizes), 1)
    samples = torch.arange(batch, device=values.device)
    sharpest = values.new_zeros(batch)
    for axis, size in enumerate(sizes):
        if size < 3:
            continue
        middle = index.clone()
        middle[:, axis] = middle[:, axis].clamp(1, size - 2)
        around = []
        for step in (-1, 0, 1):
            at = middle.clone()
            at[:, axis] += step
            around.append(values[samples, at[:, 0], at[:, 1], at[:, 2]])
        curvature = (2 * around[1] - around[0] - around[2]).clamp_min(0)
        sharpest = torch.maximum(sharpest, curvature)
    return 1 + sharpest / 12


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
        score: the name of the score they belong to (:func:`~enmi_torch.scores.as_score`).
        temperature: divide ``score * n_valid`` by it to get a log-likelihood.
        min_peak_z: the smallest robust z-score of a surface's peak that counts as a match.
        noise_model: the tracker's ``noise_model`` the surfaces were scored with
            (:class:`~enmi_torch.tracking.TrackerSettings`: ``"held"`` or ``"per_frame"``); the scale of a
            log-likelihood depends on it. ``None``: not recorded, as in calibrations made before it was: those were
            fitted per frame (the only way then), and a tracker takes them so.
    """

    score: str
    temperature: float
    min_peak_z: float
    noise_model: str | None = None

    @property
    def fitted_noise_model(self) -> str:
        """The noise model the calibration was fitted with: ``noise_model``, ``"per_frame"`` where not recorded."""
        return self.noise_model or "per_frame"

    def save(self, path: str | Path) -> Path:
        """Write the calibration as JSON (e.g. ``map_calibration.json`` next to the map), unless it could not load it.

        Raises:
            ValueError: naming the field, when ``temperature`` is not a finite number > 0 or ``min_peak_z`` is not
                finite (JSON has no NaN or inf), or ``score`` is not a score's name.
        """
        checked_calibration(self, "Calibration")
        path = Path(path)
        path.write_text(json.dumps(self._asdict(), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a calibration written by :meth:`save`, or before (its score named ``metric``, no ``noise_model``).

        A file without ``noise_model`` was written before it was recorded: fitted per frame, :attr:`fitted_noise_model`.

        Raises:
            ValueError: naming the file (and the key), when it is not a JSON object with the keys ``score`` (a score's
                name), ``temperature`` (a finite number > 0), ``min_peak_z`` (a finite number) and, optionally,
                ``noise_model`` (``"held"``, ``"per_frame"`` or null), and no other.
        """
        values = read_json(path, "calibration file")
        named = f"calibration file {str(path)!r}"
        if not isinstance(values, dict):
            raise ValueError(
                f"{named} must hold a JSON object with keys {list(cls._fields)}, got {describe_json(values)}"
            )
        if "metric" in values and "score" not in values:
            values["score"] = values.pop("metric")
        if not set(cls._fields[:3]) <= set(values) <= set(cls._fields):
            raise ValueError(
                f"{named}: a calibration needs keys {list(cls._fields[:3])} (and may have 'noise_model'), got "
                f"{sorted(values)}"
            )
        return checked_calibration(cls(**values), named)


def checked_calibration(calibration: Calibration, named: str) -> Calibration:
    """``calibration`` with float fields once each field is checked, else a ValueError that starts with ``named``."""
    score, temperature, min_peak_z, noise_model = calibration
    if not isinstance(score, str) or score not in score_names():
        raise ValueError(f"{named}: score must be one of {list(score_names())}, got {score!r}")
    for key, value in (("temperature", temperature), ("min_peak_z", min_peak_z)):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            kind = describe_json(value) if not isinstance(value, Tensor) else f"a tensor {value!r}"
            raise ValueError(f"{named}: {key} must be a finite number, got {kind}")
        if not math.isfinite(value):
            raise ValueError(f"{named}: {key} must be a finite number, got {value!r}")
    if temperature <= 0:
        raise ValueError(f"{named}: temperature must be a finite number > 0, got {temperature!r}")
    if noise_model is not None and noise_model not in NOISE_MODELS:
        raise ValueError(f"{named}: noise_model must be one of {list(NOISE_MODELS)} or None, got {noise_model!r}")
    return Calibration(score, float(temperature), float(min_peak_z), noise_model)
