"""What the drives compare: the tracker's ECR variants (a score and how its noise model is read), paired tables.

A variant is an ECR and the tracker's ``noise_model`` (:class:`~enmi_torch.tracking.TrackerSettings`):

- ``held``: ``ECR()``, its ``tau^2`` and ``delta^2`` read at the peak of a frame the tracker trusts and held
  (``noise_model="held"``);
- ``held_correlated``: the same, ``tau^2`` read with the correlated misfit (``ECR(misfit="correlated")``: its excess
  over the bins' quantisation times the pixels per independent misfit); held, it is ``ECR()`` with that number;
- ``per_frame``: ``ECR()``, every frame's surface estimating its own (``noise_model="per_frame"``);
- ``per_frame_correlated``: ``ECR(misfit="correlated")`` per frame;
- ``binned``: ``ECR(response="binned", misfit="correlated")`` per frame, the tracker's default (its score and
  ``noise_model``);
- ``binned_held``: that score with its ``tau^2`` held (the binned response has no ``delta^2``).

Per-frame argmax and oracle gating search each frame alone: a held model is the tracker's, so ``held`` searches as
``per_frame`` does there (the same score, run once).
"""

from __future__ import annotations

import argparse
import math
import statistics

from enmi_torch.scores import ECR, Score
from enmi_torch.scores.ecr import MISFITS

VARIANTS = {
    "held": (ECR(), "held"),
    "held_correlated": (ECR(misfit="correlated"), "held"),
    "per_frame": (ECR(), "per_frame"),
    "per_frame_correlated": (ECR(misfit="correlated"), "per_frame"),
    "binned": (ECR(response="binned", misfit="correlated"), "per_frame"),
    "binned_held": (ECR(response="binned", misfit="correlated"), "held"),
}
DEFAULT_VARIANT = "binned"  # the tracker's default score and noise model
VARIANT_LABELS = {
    "held": "ECR() held",
    "held_correlated": "ECR() held, tau^2 read correlated",
    "per_frame": "ECR() per frame",
    "per_frame_correlated": "ECR(correlated) per frame",
    "binned": "ECR(binned, correlated) per frame",
    "binned_held": "ECR(binned, correlated) held",
}


def variant_score(variant: str, bins: int | None = None, misfit: str | None = None) -> tuple[Score, str]:
    """The variant's ECR (with ``bins`` and ``misfit`` where given) and its ``noise_model``."""
    score, noise_model = VARIANTS[variant]
    changes = {key: value for key, value in (("bins", bins), ("misfit", misfit)) if value is not None}
    return (score.replace(**changes) if changes else score), noise_model


def mean_and_error(values: list[float]) -> str:
    """``mean ± SE`` of ``values`` (the mean alone for one value, ``-`` for none), three decimals."""
    if len(values) < 2:
        return f"{values[0]:.3f}" if values else "-"
    return f"{statistics.fmean(values):.3f} ± {statistics.stdev(values) / math.sqrt(len(values)):.3f}"


def paired_rows(
    rows: dict[str, dict[str, list[float]]], drives: int, measures: tuple[str, ...] = ("within 1 cell", "lost")
) -> list[str]:
    """Each row less the first one, drive by drive: mean ± SE of the differences (rows with every drive only)."""
    complete = {key: values for key, values in rows.items() if len(values.get(measures[0], [])) == drives}
    if len(complete) < 2 or drives < 2:
        return []
    (first, baseline), *others = complete.items()
    lines = [
        f"\nPaired on the same {drives} drives, each row less {first} (mean ± SE of the differences):\n",
        f"| method | estimator | {' | '.join(measures)} |",
        "| --- | --- |" + " --- |" * len(measures),
    ]
    for key, values in others:
        cells = [
            mean_and_error([a - b for a, b in zip(values[measure], baseline[measure], strict=True)])
            if len(values.get(measure, [])) == drives and len(baseline.get(measure, [])) == drives
            else "-"
            for measure in measures
        ]
        lines.append(f"| {key} | {' | '.join(cells)} |")
    return lines


def add_variant_options(parser: argparse.ArgumentParser) -> None:
    """The drives' ``--variants`` (a row each, default the tracker's) and ``--misfit`` (given to every variant)."""
    parser.add_argument(
        "--variants",
        nargs="+",
        choices=list(VARIANTS),
        default=[DEFAULT_VARIANT],
        help="ECR's variants, a row each: its score and how the tracker reads its noise model (default: the "
        "tracker's, binned)",
    )
    parser.add_argument("--misfit", choices=MISFITS, help="ECR's misfit in every variant (default: each variant's own)")
