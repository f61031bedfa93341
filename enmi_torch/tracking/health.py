"""The filter's health: which frames' matches are used, by the peak-z and surprise rules.

A frame whose surface has no clear peak (the robust z-score of its log-likelihood's peak, :func:`peak_z_score`, below
``min_peak_z``, or below ``z_drop`` times the recent matches') or whose peak the prediction rules out
(:func:`prediction_surprise`: more than ``max_surprise`` nats below the prediction's best) is not used in full: its
:func:`clearness` says how much of it the belief takes (none where the prediction rules it out); :class:`Health`
counts such frames per vehicle (after ``patience`` of them the tracker
relocalizes) and keeps the running peak z-score and likelihood temperature of the used matches
(:func:`next_health`), and the score each vehicle holds (its noise model fitted at a frame the tracker trusted,
:class:`~enmi_torch.tracking.TrackerSettings`' ``noise_model``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.scores import Score


class Health(NamedTuple):
    """The filter's running health per vehicle.

    Attributes:
        weak_frames: ``(B,)`` int64 consecutive frames without a usable match.
        typical_z: ``(B,)`` float64 running mean of the used matches' peak z-scores (NaN before the first).
        typical_temperature: ``(B,)`` float64 running mean of the used matches' grid temperatures
            (:func:`~enmi_torch.tracking.calibration.grid_temperature`; NaN before the first): a frame with no clear
            peak is read at the scale of the recent clear ones.
        candidate: ``(B, 3)`` float64 where the last frame's wide search found its best match, ``(x, y, yaw)``
            relative to that frame's predicted window centre (NaN when the last frame made no wide search): the
            tracker relocalizes only where two frames' wide searches agree.
        held: per vehicle, the score it holds for the coming frames (``noise_model="held"``: the tracker's score with
            its noise model fitted at the peak of a frame it trusted, :meth:`~enmi_torch.scores.Score.held_fit`), or
            ``None``: the tracker's score as it is, each frame estimating its own (before the first used frame,
            after the tracker is lost, and always with ``noise_model="per_frame"``). ``None`` for all when made
            without it.
    """

    weak_frames: Tensor
    typical_z: Tensor
    typical_temperature: Tensor
    candidate: Tensor
    held: tuple[Score | None, ...] | None = None


def check_health(health: object, batch: int, device: torch.device) -> Health:
    """The previous step's :class:`Health` checked against the batch, or a fresh one for ``None``."""
    if health is None:
        nothing = torch.full((batch,), math.nan, dtype=torch.float64, device=device)
        no_candidate = torch.full((batch, 3), math.nan, dtype=torch.float64, device=device)
        weak_frames = torch.zeros(batch, dtype=torch.int64, device=device)
        return Health(weak_frames, nothing, nothing.clone(), no_candidate, (None,) * batch)
    if (
        not isinstance(health, Health)
        or any(part.shape != (batch,) for part in health[:3])
        or health.candidate.shape != (batch, 3)
        or not (health.held is None or (isinstance(health.held, tuple) and len(health.held) == batch))
        or not all(score is None or isinstance(score, Score) for score in health.held or ())
    ):
        raise ValueError(
            f"health must be a Health of ({batch},) tensors, a ({batch}, 3) candidate and {batch} held scores (or "
            f"None) from the previous step, or None; got {health!r}"
        )
    return health if health.held is not None else health._replace(held=(None,) * batch)


def peak_z_score(surface: Tensor, min_spread: float = 0.0) -> Tensor:
    """Robust z-score of the best value of a surface: ``(best - median) / max(1.4826 MAD, min_spread)``.

    ``min_spread``: the smallest spread counted, in the surface's units. The tracker passes log-likelihoods in nats
    with ``min_spread=1``: a nearly flat surface (a featureless frame, a MAD of hundredths of a nat) would otherwise
    get an enormous z-score for a peak of a few nats.
    """
    values = surface.flatten()
    median = values.median()
    spread = (1.4826 * (values - median).abs().median()).clamp_min(min_spread)
    return (values.max() - median) / spread.clamp_min(1e-12 * values.abs().max().clamp_min(1e-300))


def prediction_surprise(log_prior: Tensor, log_likelihood: Tensor) -> Tensor:
    """``(B,)`` nats by which the prediction puts the likelihood's peak below the prediction's own best."""
    flat_likelihood, flat_prior = log_likelihood.flatten(1), log_prior.flatten(1)
    index = flat_likelihood.argmax(1, keepdim=True)
    return flat_prior.amax(1) - flat_prior.gather(1, index)[:, 0]


def clearness(peak_z: Tensor, surprise: Tensor, health: Health, min_peak_z: float, z_drop: float, max_surprise: float):
    """``(B,)`` float64 in ``[0, 1]``: how much of a frame's log-likelihood the belief takes.

    1 for a clear peak the prediction allows, a frame used in full: ``peak_z`` at least ``threshold``, the larger of
    ``min_peak_z`` and ``z_drop`` times the recent matches' z-score (a peak far weaker than those is a match of some
    other place: a kidnap, a wrong window). ``(peak_z / threshold)^2`` for a weaker peak the prediction allows (it
    nudges the belief instead of being dropped); 0 for a peak the prediction rules out (``surprise > max_surprise``)
    or a frame without candidates.
    """
    typical = torch.where(torch.isfinite(health.typical_z), health.typical_z, peak_z)
    threshold = torch.maximum(torch.full_like(peak_z, min_peak_z), z_drop * typical)
    weight = (peak_z.double() / threshold.double()).clamp(0, 1).square()
    allowed = torch.isfinite(weight) & (surprise <= max_surprise)
    return torch.where(allowed, weight, 0.0)


def next_health(
    health: Health,
    healthy: Tensor,
    relocalized: Tensor,
    weak_frames: Tensor,
    peak_z: Tensor,
    temperature: Tensor,
    candidate: Tensor,
) -> Health:
    """The health after a frame: ``weak_frames`` so far, the running peak z-score and temperature of the used matches.

    ``temperature`` ``(B,)`` is each frame's own grid temperature (NaN where it has none); ``candidate`` ``(B, 3)``
    this frame's wide-search match (NaN where none was made), dropped where the frame was used.
    """
    weak_frames = torch.where(healthy, 0, weak_frames)
    typical_z = _running(health.typical_z, peak_z, healthy, relocalized)
    typical_temperature = _running(health.typical_temperature, temperature, healthy, relocalized)
    candidate = torch.where(healthy[:, None], math.nan, candidate)
    return Health(weak_frames, typical_z, typical_temperature, candidate, health.held)


def _running(old: Tensor, new: Tensor, healthy: Tensor, relocalized: Tensor) -> Tensor:
    """A running mean (0.3 on the newest) over the used matches; a relocalization or the first match resets it.

    A new value counts at most twice the running mean: one freak peak (a z-score of 90 where the matches run at 7)
    would otherwise make every later match look weak next to it.
    """
    fresh = relocalized | ~torch.isfinite(old)
    used = healthy & torch.isfinite(new)
    new = torch.where(fresh, new, torch.minimum(new, 2 * old))
    return torch.where(used, torch.where(fresh, new, 0.7 * old + 0.3 * new), old)
