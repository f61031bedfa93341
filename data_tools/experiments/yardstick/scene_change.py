"""Does the per-pixel variance pay where the scene changed? Localization success against controls, paired trials.

Each trial cuts a 64 x 64 captured image at a known shift within +-12 cells (yaw 0) of an 88 x 88 map window and
searches the 25 x 25 shifts with every method on the same noisy image (common random numbers: the same poses, scene
changes and standard-normal draws, scaled, for every method and noise level). Success: the best shift within one
cell of the truth on both axes.

Cases:

* noise only: ``same`` (the captured image is the map itself, as ``yardstick.py``) and ``nonmonotonic`` (the map
  through ``yardstick.py``'s non-monotonic response, ``255 |2 v / 255 - 1|^0.8``);
* ``<change>@<strength>``: the map window changed by :mod:`enmi_torch.data.scene_change` (``illumination``,
  ``shadows``, ``occluders``, ``tone``, ``resample_blur``, ``warp``, or ``mixed``: all of them) before the captured
  image is cut from it; maps are the photographs of ``yardstick.py`` (one drawn per trial);
* ``same:<case>[/<dataset>]`` (noise only): the reference photographs of real pairs (below) against themselves;
* ``real:<case>/<dataset>``: real pairs from ``--data DIR`` (``DIR/<case>/<dataset>-<id>/reference.npy`` and
  ``captured.npy``, grey levels in [0, 255], co-registered; one pair of the dataset drawn per trial; ``real:<case>``:
  all its datasets), when the folder is there; ``data.json`` lists the pair folders each case drew from
  (``--real-folders even`` / ``odd``: every other folder of each dataset, for masks learned on the other half).

Sensors: ``camera-like`` (far rows ~100x noisier), ``lidar-like`` (~100x at the corners) and, for the noise-only cases,
``paper-camera`` (the paper's road camera, unseen cells left out): the profiles of ``yardstick.py``, scaled so that the
mean noise standard deviation over the valid pixels is the level; the noisy grey levels are clipped to 0..255.999 as a
sensor saturates (``--no-clip``: not). Levels per case and sensor: the hardest level where some method of
:data:`CALIBRATION_METHODS` (every score of the table, NCC and the linear response included; ``--calibration-methods``)
still succeeds half the time (``L50``, from a calibration pass on trials of their own, recorded with each method's rates
in ``calibration.json``), times ``--fractions`` (``L50 / 4`` and ``L50``); the noise-only cases also at
``--same-levels``; or ``--levels`` for every cell. ``--calibration`` reuses an earlier run's levels (same trials, same
levels: a re-run after a change of the default) where it was calibrated on the same methods and clipping.

Methods (32 bins; :data:`METHODS` says which score with which variance): ``ECR true`` (the default ``ECR()``: its model
variance ``tau^2`` estimated from the data, with the true per-pixel variance); ``ECR regional true``
(``ECR(misfit="regional")``: a model variance per captured pixel, issue 33); ``ECR binned true``
(``response="binned"``, the default before issue 33, its control); ``ECR today`` (``tau^2`` fixed at ``bin_width^2 /
12``, the default before the estimate); ``ECR tau 1024`` / ``4096`` (``tau^2`` fixed); ``ECR correlated true``
(``ECR(misfit="correlated")``: the misfit counted per independent patch); ``ECR capped true`` (the true variance capped
at a quarter of the clipping range squared, the most a clipped grey level can vary); ``ECR regional at truth`` and
``ECR regional at its peak`` (the regional misfit map read at the true placement, an oracle, and at the best placement
of the default's surface, added to the true variance); ECR and ENMI with one uniform variance, the true map's mean
times 1/16, 1/4, 1, 4, 16 (``uniform mean`` is x1, ``best uniform`` the best of the five per cell, an oracle); ``ECR
linear true`` and ``ECR linear uniform`` (``response="linear"`` with the true variance
and with its mean); ENMI true; NMI; NCC; and ``ECR learned``: ``ECR()`` with the variance mask of ``--learned-mask``
(a ``(64, 64)`` ``.npy`` variance map, e.g. the ``mask/variance_mask.npy`` that ``train/fit_mask.py`` writes from the
pairs of ``data_tools/experiments/mask/scene_change_pairs.py``), for runs at the level that mask was learned at.

The report gives each method's success, and each method minus ``ECR true`` paired per trial with its SE.

Writes ``results.csv`` (outcomes per trial as bits, and the estimated ``tau^2`` per trial for ``ECR true`` and ``ECR
learned``), ``calibration.json``, ``data.json`` and ``report.md`` into ``--output`` (refusing files git tracks), and
prints the report.

    # a minute or two
    python -m data_tools.experiments.yardstick.scene_change --trials 12 --cases same tone@1 --output /tmp/sc
    python -m data_tools.experiments.yardstick.scene_change --trials 100 --jobs 2  # the full table
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import subprocess
import sys
import time
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from data_tools.experiments.yardstick import yardstick
from enmi_torch import ECR, ENMI, NCC, NMI
from enmi_torch.data.scene_change import CHANGES, scene_change
from enmi_torch.localization import SearchStrategy, localize
from enmi_torch.scores.ecr import default_model_variance, ecr_model_variance
from enmi_torch.utils.files import read_npy

NOISE_ONLY = yardstick  # the noise-only yardstick: maps, profiles, response, success rule
LOCAL, RADIUS, BINS = NOISE_ONLY.LOCAL, NOISE_ONLY.RADIUS, NOISE_ONLY.BINS
VALUE_RANGE = (0.0, 256.0)
SPAN = LOCAL + 2 * RADIUS
SENSORS = ("camera-like", "lidar-like", "paper-camera")
NOISE_ONLY_CASES = ("same", "nonmonotonic")
KINDS = (*CHANGES, "mixed")
CASES = ("same", *(f"{kind}@{strength}" for kind in CHANGES for strength in (0.5, 1)), "mixed@0.25", "mixed@0.35")
# Cases run after --data's real ones: each case's seed is its position, so those before keep the seeds of earlier runs.
LATER_CASES = ("nonmonotonic",)
GRID = (1 / 16, 1 / 4, 1.0, 4.0, 16.0)
CALIBRATION_LEVELS = (4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0, 1024.0, 2048.0)
# L50 is the hardest level where some method succeeds half the time, correlation and the linear response included.
CALIBRATION_METHODS = (
    "ECR true",
    "ECR binned true",
    "ECR uniform x1",
    "ECR linear true",
    "ECR linear uniform",
    "ENMI uniform x1",
    "NMI",
    "NCC",
)
# The calibration before issue 33: the information scores only (their levels stopped where NCC still succeeds).
INFORMATION_METHODS = ("ECR true", "ECR uniform x1", "ENMI uniform x1", "NMI")
# A sensor's digitiser saturates: noisy grey levels are clipped into [0, 256) like an 8-bit image with its fraction.
CLIP_RANGE = (0.0, 255.999)
CHUNK = 25  # trials per surface call: memory stays small
# Today's fixed model variance: the spread of an amplitude uniform in one of the 32 bins.
TODAY = default_model_variance(BINS, VALUE_RANGE)


class Context(NamedTuple):
    """One chunk of trials at one level: what every method sees."""

    local: torch.Tensor  # (T, 1, LOCAL, LOCAL) float32 noisy captured images
    window: torch.Tensor  # (T, 1, SPAN, SPAN) float32 map windows
    variance: torch.Tensor  # (1, 1, LOCAL, LOCAL) float32 true noise variance
    mean: float  # the true variance's mean over the valid pixels
    truth: torch.Tensor  # (T, 2) true placement (row, col)
    mask: torch.Tensor | None  # (1, 1, LOCAL, LOCAL) bool valid pixels, None when all are
    learned: torch.Tensor | None  # (1, 1, LOCAL, LOCAL) float32 learned variance mask


def _factor_name(factor: float) -> str:
    return f"x{factor:g}"


# Which score with which variance: "true" (the sensor's map), "capped" (the true map capped at what a clipped grey
# level can vary), "learned" (--learned-mask), a factor of the true map's mean (one uniform variance), or None (a score
# without a variance). Each searches as localize does, with its default finalist stage (the surface's best local
# maxima rescored by the score on each aligned pair: ECR's estimated tau^2 and delta^2 and its censored readings);
# the methods of SURFACE_ONLY take the surface's maximum as it is.
METHODS: dict[str, tuple] = {
    "ECR true": (ECR(bins=BINS), "true"),
    "ECR surface true": (ECR(bins=BINS), "true"),
    "ECR Gaussian true": (ECR(bins=BINS, saturation=None), "true"),
    "ECR before true": (ECR(bins=BINS, saturation=None), "true"),
    "ECR today": (ECR(bins=BINS, model_variance=TODAY), "true"),
    "ECR regional true": (ECR(bins=BINS, misfit="regional"), "true"),
    "ECR learned": (ECR(bins=BINS), "learned"),
    **{f"ECR uniform {_factor_name(factor)}": (ECR(bins=BINS), factor) for factor in GRID},
    "ECR binned true": (ECR(bins=BINS, response="binned"), "true"),
    "ECR linear true": (ECR(bins=BINS, response="linear"), "true"),
    "ECR linear uniform": (ECR(bins=BINS, response="linear"), 1.0),
    "ENMI true": (ENMI(bins=BINS), "true"),
    **{f"ENMI uniform {_factor_name(factor)}": (ENMI(bins=BINS), factor) for factor in GRID},
    "NMI": (NMI(bins=BINS), None),
    "NCC": (NCC(), None),
    "ECR tau 1024": (ECR(bins=BINS, model_variance=1024.0), "true"),
    "ECR tau 4096": (ECR(bins=BINS, model_variance=4096.0), "true"),
    "ECR correlated true": (ECR(bins=BINS, misfit="correlated"), "true"),
    "ECR capped true": (ECR(bins=BINS), "capped"),
    # The regional misfit map read with the captured image at the true placement (an oracle no search has), and at the
    # best placement of the default's surface; added to the true variance (model variance 0), held at every placement.
    "ECR regional at truth": (ECR(bins=BINS, model_variance=0.0), "regional at truth"),
    "ECR regional at its peak": (ECR(bins=BINS, model_variance=0.0), "regional at peak"),
}
DEFAULT_METHODS = tuple(method for method in METHODS if method != "ECR learned")
# The surface's maximum, no finalist stage: the default's surface alone, and the default of the last release (its
# readings Gaussian, issue 33's "ECR true").
SURFACE_ONLY = ("ECR surface true", "ECR before true")
FINALISTS = SearchStrategy().finalists
# Methods whose estimated tau^2 is recorded per trial.
ESTIMATED = ("ECR true", "ECR learned")
# Columns of the report: the grids collapse into their mean and their best (picked per cell after the fact).
DERIVED = {"ECR uniform mean": "ECR uniform x1", "ENMI uniform mean": "ENMI uniform x1"}
BEST = {"ECR best uniform": "ECR uniform ", "ENMI best uniform": "ENMI uniform "}
CONTROLS = (
    "ECR uniform mean",
    "ECR best uniform",
    "ECR binned true",
    "ECR linear true",
    "ECR linear uniform",
    "ENMI best uniform",
    "NMI",
    "NCC",
)
CANDIDATES = ("ECR true", "ECR regional true", "ECR learned", "ECR today")
SHOWN = (
    "ECR true",
    "ECR surface true",
    "ECR Gaussian true",
    "ECR before true",
    "ECR regional true",
    "ECR learned",
    "ECR today",
    "ECR uniform mean",
    "ECR best uniform",
    "ECR binned true",
    "ECR linear true",
    "ECR linear uniform",
    "ENMI true",
    "ENMI best uniform",
    "NMI",
    "NCC",
    "ECR tau 1024",
    "ECR tau 4096",
    "ECR correlated true",
    "ECR capped true",
    "ECR regional at truth",
    "ECR regional at its peak",
)


class Trials(NamedTuple):
    """The trials of one case, before noise."""

    clean: torch.Tensor  # (T, 1, LOCAL, LOCAL) float64 noiseless captured images
    window: torch.Tensor  # (T, 1, SPAN, SPAN) float64 map windows
    truth: torch.Tensor  # (T, 2) int64
    draws: torch.Tensor  # (T, 1, LOCAL, LOCAL) float64 standard-normal draws


REAL_PREFIXES = ("real:", "same:")


def real_name(case: str) -> str | None:
    """The pair folders a case draws from (``another-date/levir-cd`` of ``real:`` or ``same:``), else None."""
    return next((case[len(prefix) :] for prefix in REAL_PREFIXES if case.startswith(prefix)), None)


def is_noise_only(case: str) -> bool:
    """``same``, ``nonmonotonic`` and ``same:<folder>`` (the real pairs' reference photographs against themselves)."""
    return case in NOISE_ONLY_CASES or case.startswith("same:")


def parse_case(case: str) -> tuple[str, float]:
    """``(kind, strength)`` of a case name: ``same`` -> ``("same", 0)``, ``tone@0.5``, ``real:another-date``."""
    if case in NOISE_ONLY_CASES or real_name(case):
        return case, 0.0
    kind, _, strength = case.partition("@")
    if kind not in KINDS or not strength:
        raise ValueError(
            f"case must be one of {list(NOISE_ONLY_CASES)}, 'real:<folder>', 'same:<folder>' or '<change>@<strength>'"
            f" with change in {list(KINDS)}, got {case!r}"
        )
    value = float(strength)
    if not 0 < value <= 1:
        raise ValueError(f"the strength of case {case!r} must be in (0, 1]")
    return kind, value


def dataset_of(folder: Path) -> str:
    """A pair folder's dataset: ``meta.json``'s ``"dataset"``, else the folder name less its last ``-<id>``."""
    meta = folder / "meta.json"
    if meta.exists():
        try:
            return str(json.loads(meta.read_text())["dataset"])
        except (ValueError, KeyError):
            pass
    return folder.name.rsplit("-", 1)[0]


REAL_FOLDERS = ("all", "even", "odd")


def pair_folders(data: Path, name: str, half: str = "all") -> list[Path]:
    """The pair folders of ``name``: ``<case>`` (all of ``data/<case>/``) or ``<case>/<dataset>``.

    ``half``: ``"all"``, or ``"even"`` / ``"odd"``: the folders at even / odd positions of each dataset's sorted list
    (a split of the places: a mask learned on one half, measured on the other).
    """
    case, _, dataset = name.partition("/")
    if not (data / case).is_dir():
        raise ValueError(f"--data: no folder {data / case} for case 'real:{name}'")
    folders = [
        path
        for path in sorted((data / case).iterdir())
        if path.is_dir()
        and (path / "reference.npy").exists()
        and (path / "captured.npy").exists()
        and (not dataset or dataset_of(path) == dataset)
    ]
    if half != "all":
        position: dict[str, int] = {}
        kept = []
        for path in folders:
            index = position[dataset_of(path)] = position.get(dataset_of(path), -1) + 1
            if index % 2 == (0 if half == "even" else 1):
                kept.append(path)
        folders = kept
    if not folders:
        raise ValueError(f"--data: no pair folder for case 'real:{name}' under {data / case} ({half} folders)")
    return folders


def real_pairs(data: Path, name: str, half: str = "all", size: int = SPAN) -> list[tuple[np.ndarray, np.ndarray]]:
    """The ``(reference, captured)`` grey arrays of :func:`pair_folders`, those at least ``size`` on each side."""
    pairs = []
    for folder in pair_folders(data, name, half):
        reference = read_npy(folder / "reference.npy", "--data").astype(np.float64)
        captured = read_npy(folder / "captured.npy", "--data").astype(np.float64)
        if reference.ndim == 3:
            reference, captured = reference.mean(-1), captured.mean(-1)
        if reference.shape != captured.shape:
            raise ValueError(f"--data: {folder} holds reference {reference.shape} and captured {captured.shape}")
        if min(reference.shape) >= size:
            pairs.append((reference, captured))
    if not pairs:
        raise ValueError(f"--data: no pair of at least {size} x {size} for case 'real:{name}'")
    return pairs


def real_cases(data: Path | None) -> list[str]:
    """One case per case folder and dataset (:func:`dataset_of`): ``real:another-date/oscd``, ..."""
    if data is None or not data.is_dir():
        return []
    names = []
    for case in sorted(path for path in data.iterdir() if path.is_dir()):
        datasets = sorted({dataset_of(folder) for folder in case.iterdir() if (folder / "captured.npy").exists()})
        names += [f"real:{case.name}/{dataset}" for dataset in datasets]
    return names


def make_trials(case: str, trials: int, seed: int, data: Path | None = None, half: str = "all") -> Trials:
    """The trials of one case: poses, scene changes and noise draws, a function of ``(case, trials, seed)``."""
    kind, strength = parse_case(case)
    generator = torch.Generator().manual_seed(seed)
    if kind.startswith("real:"):
        sources = [(torch.from_numpy(r), torch.from_numpy(c)) for r, c in real_pairs(data, kind[5:], half)]
    elif kind.startswith("same:"):
        sources = [(torch.from_numpy(r), torch.from_numpy(r)) for r, _ in real_pairs(data, kind[5:], half)]
    else:
        maps = [NOISE_ONLY.map_image(name) for name in NOISE_ONLY.MAPS]
        sources = [(image, image) for image in maps]
    clean, windows, truth = [], [], []
    for trial in range(trials):
        reference, captured = sources[int(torch.randint(len(sources), (), generator=generator))]
        top = int(torch.randint(reference.shape[0] - SPAN + 1, (), generator=generator))
        left = int(torch.randint(reference.shape[1] - SPAN + 1, (), generator=generator))
        shift = torch.randint(-RADIUS + 1, RADIUS, (2,), generator=generator)
        window = reference[top : top + SPAN, left : left + SPAN]
        scene = captured[top : top + SPAN, left : left + SPAN]
        if kind == "nonmonotonic":
            scene = NOISE_ONLY.respond(scene, "nonmonotonic")
        elif kind != "same" and not real_name(kind):
            kinds = tuple(CHANGES) if kind == "mixed" else (kind,)
            scene = scene_change(scene, seed * 100003 + trial, strength, kinds=kinds)
        row, col = (shift + RADIUS).tolist()
        clean.append(scene[row : row + LOCAL, col : col + LOCAL])
        windows.append(window)
        truth.append((row, col))
    draws = torch.randn(trials, 1, LOCAL, LOCAL, generator=generator, dtype=torch.float64)
    return Trials(
        torch.stack(clean)[:, None].double(), torch.stack(windows)[:, None].double(), torch.tensor(truth), draws
    )


def noisy(trials: Trials, sensor: str, level: float, clip: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """The noisy captured images (float64) and the true variance ``(1, 1, LOCAL, LOCAL)`` at ``level``.

    The noise is clipped to :data:`CLIP_RANGE` when ``clip``, as a sensor saturates (the true variance passed to the
    scores stays the sensor's); pixels the sensor does not see are 0.
    """
    unit, valid = NOISE_ONLY.variance_profile(sensor)
    variance = (level**2 * unit)[None, None]
    local = trials.clean + trials.draws * variance.sqrt()
    if clip:
        local = local.clamp(*CLIP_RANGE)
    return local.where(valid, 0.0), variance


def _contexts(trials: Trials, sensor: str, level: float, learned: torch.Tensor | None = None, clip: bool = True):
    _, valid = NOISE_ONLY.variance_profile(sensor)
    local, variance = noisy(trials, sensor, level, clip)
    local = local.float()
    mean = float(variance[0, 0][valid].mean())
    mask = None if bool(valid.all()) else valid[None, None]
    for start in range(0, local.shape[0], CHUNK):
        part = slice(start, start + CHUNK)
        window = trials.window[part].float()
        yield Context(local[part], window, variance.float(), mean, trials.truth[part], mask, learned)


def _with_regional_misfit(context: Context, placements: torch.Tensor) -> torch.Tensor:
    """``(T, 1, h, w)``: the true variance plus ``ECR(misfit="regional")``'s map, read at ``placements`` ``(T, 2)``."""
    size = context.local.shape[-1]
    sections = torch.stack(
        [
            context.window[index, :, row : row + size, col : col + size]
            for index, (row, col) in enumerate(placements.tolist())
        ]
    )
    misfit = ecr_model_variance(
        context.local, sections, context.variance, bins=BINS, valid_mask=context.mask, misfit="regional"
    )
    return context.variance + misfit[:, None].to(context.variance.dtype)


def _variance(context: Context, kind):
    """The variance a method gives its score: the true map, the learned mask, a uniform one or none."""
    if kind == "true":
        return context.variance
    if kind == "capped":  # no variable within the clipping range varies more (Popoviciu's inequality)
        return context.variance.clamp_max((CLIP_RANGE[1] - CLIP_RANGE[0]) ** 2 / 4)
    if kind == "regional at truth":
        return _with_regional_misfit(context, context.truth)
    if kind == "regional at peak":
        score = METHODS["ECR true"][0].surface(
            context.local, context.window, context.variance, captured_mask=context.mask
        )
        columns = score.score.shape[-1]
        peak = score.score.flatten(1).argmax(1)
        return _with_regional_misfit(context, torch.stack([peak // columns, peak % columns], 1))
    if kind == "learned":
        if context.learned is None:
            raise ValueError("method 'ECR learned' needs --learned-mask")
        return context.learned
    return None if kind is None else context.mean * kind


def searched(score, context: Context, variance, finalists: int = FINALISTS) -> torch.Tensor:
    """``(T, 2)`` the placement (row, column) ``localize`` picks in each trial's window: the surface, its finalists."""
    middle = LOCAL // 2 + RADIUS  # shift 0 puts the captured image on the window's middle cell (x, y)
    found = localize(
        context.local,
        context.window,
        variance,
        score=score,
        shifts=RADIUS,
        around=(middle, middle),
        captured_mask=context.mask,
        search=SearchStrategy(finalists=finalists),
    )
    if found.finalists is not None:
        return found.finalists.best()[:, 1:]
    columns = found.surface.shape[-1]
    peak = found.surface.flatten(1).argmax(1)
    return torch.stack([peak // columns, peak % columns], 1)


def run_methods(trials: Trials, sensor: str, level: float, methods, learned=None, clip=True) -> dict[str, tuple]:
    """Per method: success per trial (bool ``(T,)``) and the estimated ``tau^2`` per trial (empty when not kept)."""
    torch.set_num_threads(1)
    success = {method: [] for method in methods}
    tau2 = {method: [] for method in methods}
    for context in _contexts(trials, sensor, level, learned, clip):
        for method in methods:
            score, kind = METHODS[method]
            variance = _variance(context, kind)
            found = searched(score, context, variance, 0 if method in SURFACE_ONLY else FINALISTS)
            success[method].append(((found - context.truth).abs() <= 1).all(1))
            if method in ESTIMATED:
                estimate = score.surface_model_variance(
                    context.local, context.window, variance, captured_mask=context.mask
                )
                tau2[method] += estimate.tolist()
    return {method: (torch.cat(success[method]), tau2[method]) for method in methods}


def calibrate(
    case: str,
    sensor: str,
    trials: int,
    seed: int,
    data: Path | None,
    methods: tuple[str, ...] = CALIBRATION_METHODS,
    clip: bool = True,
) -> dict:
    """Success of ``methods`` per level and ``L50``: the hardest level where the best of them reaches 1/2.

    ``L50`` interpolates the best rate linearly in ``log level`` between the last level at or above 1/2 and the next;
    when no level reaches 1/2 it is the lowest level, when all do the highest (``bracketed`` says which). ``rates``
    holds each method's rate per level, ``leader`` the best method at the last level at or above 1/2.
    """
    torch.set_num_threads(1)
    generated = make_trials(case, trials, seed, data)
    best, rates = [], {method: [] for method in methods}
    for level in CALIBRATION_LEVELS:
        results = run_methods(generated, sensor, level, methods, clip=clip)
        for method, (outcome, _) in results.items():
            rates[method].append(float(outcome.double().mean()))
        best.append(max(rate[-1] for rate in rates.values()))
        if len(best) >= 2 and best[-1] < 0.25 and best[-2] < 0.5:
            break  # success falls with noise: the levels beyond are not needed
    above = [index for index, rate in enumerate(best) if rate >= 0.5]
    if not above:
        level, bracketed = CALIBRATION_LEVELS[0], "below"
    elif above[-1] == len(best) - 1:
        level, bracketed = CALIBRATION_LEVELS[len(best) - 1], "above" if len(best) == len(CALIBRATION_LEVELS) else "yes"
    else:
        index = above[-1]
        low, high = best[index], best[index + 1]
        fraction = (low - 0.5) / (low - high) if low > high else 0.0
        level = math.exp(
            math.log(CALIBRATION_LEVELS[index])
            + fraction * (math.log(CALIBRATION_LEVELS[index + 1]) - math.log(CALIBRATION_LEVELS[index]))
        )
        bracketed = "yes"
    level = float(f"{level:.2g}")
    index = above[-1] if above else 0
    leader = max(methods, key=lambda method: rates[method][index])
    return {
        "case": case,
        "sensor": sensor,
        "L50": level,
        "bracketed": bracketed,
        "best_rates": best,
        "methods": list(methods),
        "clip": clip,
        "rates": rates,
        "leader": leader,
    }


def run_cell(case, sensor, levels, trials, seed, data, methods, half="all", learned=None, clip=True) -> list:
    """Rows ``(case, sensor, level, method, successes, trials, outcomes, tau2s)`` of one case and sensor."""
    generated = make_trials(case, trials, seed, data, half)
    rows = []
    for level in levels:
        for method, (success, tau2) in run_methods(generated, sensor, level, methods, learned, clip).items():
            bits = "".join("1" if value else "0" for value in success.tolist())
            tau_text = " ".join(f"{value:.4g}" for value in tau2)
            rows.append((case, sensor, level, method, int(success.sum()), trials, bits, tau_text))
    return rows


def outcome_bits(text: str) -> np.ndarray:
    """A ``results.csv`` outcomes string (one ``0``/``1`` per trial) as an integer array."""
    return np.array([int(bit) for bit in text])


def paired_difference(first: np.ndarray, second: np.ndarray) -> tuple[float, float]:
    """Mean and standard error of ``first - second`` over paired trials (standard error 0 for a single trial)."""
    if len(first) != len(second):
        raise ValueError(f"paired outcomes must have the same length, got {len(first)} and {len(second)}")
    difference = first - second
    error = difference.std(ddof=1) / math.sqrt(len(difference)) if len(difference) > 1 else 0.0
    return float(difference.mean()), float(error)


def cell_outcomes(rows: list) -> dict:
    """``{(case, sensor, level): {method: outcomes}}`` with the derived columns (uniform mean, best uniform)."""
    cells: dict = {}
    for case, sensor, level, method, _, _, bits, _ in rows:
        cells.setdefault((case, sensor, float(level)), {})[method] = outcome_bits(bits)
    for outcomes in cells.values():
        for name, source in DERIVED.items():
            if source in outcomes:
                outcomes[name] = outcomes[source]
        for name, prefix in BEST.items():
            grid = {method: bits for method, bits in outcomes.items() if method.startswith(prefix)}
            if grid:
                # Ties go to x1 (the mean), then to the smaller factor.
                best = max(grid, key=lambda method: (grid[method].sum(), method == prefix + "x1"))
                outcomes[name] = grid[best]
                outcomes[name + " factor"] = best[len(prefix) :]
    return cells


def group_of(case: str) -> str:
    """The cell's group: noise only, controlled change or real pairs."""
    if is_noise_only(case):
        return "noise only"
    return "real pairs" if case.startswith("real:") else "controlled change"


def _rate(bits: np.ndarray) -> str:
    rate = bits.mean()
    return f"{rate:.2f} ± {math.sqrt(rate * (1 - rate) / len(bits)):.2f}"


def _against_default(cells: dict, keys: list, shown: list, base: str = "ECR true") -> list[str]:
    """Each method minus ``base`` (the default), paired per trial: per cell, per group and over all cells."""
    others = [method for method in shown if method != base and any(method in cells[key] for key in keys)]
    if not others or not any(base in cells[key] for key in keys):
        return []
    lines = ["", f"## Paired differences: each method minus {base} (success rate, mean ± SE over the trials)", ""]
    lines += ["| case | sensor | sigma | " + " | ".join(others) + " |", "|---|---|---|" + "---|" * len(others)]

    def text(members, method):
        judged = [key for key in members if method in cells[key] and base in cells[key]]
        if not judged:
            return ""
        mean, error = paired_difference(
            np.concatenate([cells[key][method] for key in judged]),
            np.concatenate([cells[key][base] for key in judged]),
        )
        mark = " **" if abs(mean) > 2 * error + 1e-12 else ""
        return f"{mean:+.3f} ± {error:.3f}{mark}"

    for key in keys:
        lines.append(f"| {key[0]} | {key[1]} | {key[2]:g} | " + " | ".join(text([key], m) for m in others) + " |")
    for group in ("noise only", "controlled change", "real pairs", "all"):
        members = [key for key in keys if group == "all" or group_of(key[0]) == group]
        if members:
            lines.append(
                f"| {group}, pooled | {len(members)} cells | | " + " | ".join(text(members, m) for m in others) + " |"
            )
    lines += ["", "(** more than 2 SE from zero)"]
    return lines


def report(rows: list, calibration: list) -> str:
    """The markdown report: success tables, groups, paired claims of the candidates against the controls, ``tau^2``."""
    cells = cell_outcomes(rows)
    keys = list(cells)
    shown = [method for method in SHOWN if any(method in cells[key] for key in keys)]
    lines = []
    if calibration:
        methods = calibration[0].get("methods", INFORMATION_METHODS)
        clipped = "clipped" if calibration[0].get("clip", False) else "not clipped"
        lines += [f"## Calibration: L50 per case and sensor (best of {', '.join(methods)}; {clipped})", ""]
        lines += [
            "| case | sensor | L50 | bracketed | best at L50 | best rate per level (from 4, x2 each) |",
            "|---|---|---|---|---|---|",
        ]
        for entry in calibration:
            rates = " ".join(f"{rate:.2f}" for rate in entry["best_rates"])
            lines.append(
                f"| {entry['case']} | {entry['sensor']} | {entry['L50']:g} | {entry['bracketed']} | "
                f"{entry.get('leader', '')} | {rates} |"
            )
        lines.append("")
    trials = len(next(iter(cells[keys[0]].values())))
    lines += [f"## Success rate ± SE ({trials} paired trials per cell)", ""]
    lines += ["| case | sensor | sigma | " + " | ".join(shown) + " |", "|---|---|---|" + "---|" * len(shown)]
    for key in keys:
        texts = []
        for method in shown:
            if method not in cells[key]:
                texts.append("")
                continue
            text = _rate(cells[key][method])
            if method.endswith("best uniform"):
                text += f" ({cells[key][method + ' factor']})"
            texts.append(text)
        lines.append(f"| {key[0]} | {key[1]} | {key[2]:g} | " + " | ".join(texts) + " |")
    lines += ["", "## Mean success per group of cells (pooled successes of all trials in the last row)", ""]
    lines += ["| group | cells | " + " | ".join(shown) + " |", "|---|---|" + "---|" * len(shown)]
    for group in ("noise only", "controlled change", "real pairs"):
        members = [key for key in keys if group_of(key[0]) == group]
        if members:
            means = [
                f"{np.mean([cells[key][m].mean() for key in members if m in cells[key]]):.3f}"
                if any(m in cells[key] for key in members)
                else ""
                for m in shown
            ]
            lines.append(f"| {group} | {len(members)} | " + " | ".join(means) + " |")
    totals = [
        f"{sum(int(cells[key][m].sum()) for key in keys if m in cells[key])} of "
        f"{sum(len(cells[key][m]) for key in keys if m in cells[key])}"
        for m in shown
    ]
    lines.append(f"| pooled | {len(keys)} | " + " | ".join(totals) + " |")
    lines += _against_default(cells, keys, shown)
    lines += _against_default(cells, keys, shown, "ECR regional true")  # issue 33's regional misfit
    lines += ["", "## Paired differences: ECR true (estimated tau^2) minus ECR today, all trials of each group", ""]
    for group in ("noise only", "controlled change", "real pairs", "all"):
        members = [key for key in keys if group == "all" or group_of(key[0]) == group]
        pairs = [(cells[key]["ECR true"], cells[key]["ECR today"]) for key in members if "ECR today" in cells[key]]
        if pairs and all("ECR true" in cells[key] for key in members):
            mean, error = paired_difference(
                np.concatenate([a for a, _ in pairs]), np.concatenate([b for _, b in pairs])
            )
            lines.append(f"- {group} ({len(pairs)} cells): {mean:+.4f} ± {error:.4f}")
    lines += ["", "## Paired differences: cells where a candidate is more than 1 SE below a control", ""]
    lines += ["| candidate | cells | " + " | ".join(CONTROLS) + " |", "|---|---|" + "---|" * len(CONTROLS)]
    failures_text = []
    for candidate in CANDIDATES:
        for scope, inside in (("scene change", lambda case: not is_noise_only(case)), ("noise only", None)):
            judged_keys = [
                key for key in keys if candidate in cells[key] and (inside(key[0]) if inside else is_noise_only(key[0]))
            ]
            if not judged_keys:
                continue
            counts_text = []
            for control in CONTROLS:
                judged = [key for key in judged_keys if control in cells[key]]
                failures = []
                for key in judged:
                    mean, error = paired_difference(cells[key][candidate], cells[key][control])
                    if mean < -error - 1e-12:
                        mark = " (> 2 SE)" if mean < -2 * error - 1e-12 else ""
                        failures.append(f"{key[0]}/{key[1]}/{key[2]:g}: {mean:+.2f} ± {error:.2f}{mark}")
                counts_text.append(f"{len(judged) - len(failures)}/{len(judged)}")
                if failures:
                    failures_text.append(f"- {candidate} vs {control} ({scope}): " + "; ".join(failures))
            lines.append(f"| {candidate} | {scope} | " + " | ".join(counts_text) + " |")
    lines += ["", "(within 1 SE or above / cells judged)", "", *failures_text]
    if any("ECR learned" in cells[key] for key in keys):
        lines += ["", "## ECR learned against ECR true (the analytic map) and ECR with a uniform variance", ""]
        for control in ("ECR true", "ECR today", "ECR uniform mean", "ECR best uniform"):
            judged = [key for key in keys if "ECR learned" in cells[key] and control in cells[key]]
            if not judged:
                continue  # that control was not run
            below = []
            for key in judged:
                mean, error = paired_difference(cells[key]["ECR learned"], cells[key][control])
                if mean < -error - 1e-12:
                    below.append(f"{key[0]}/{key[1]}/{key[2]:g}: {mean:+.2f} ± {error:.2f}")
            everything = paired_difference(
                np.concatenate([cells[key]["ECR learned"] for key in judged]),
                np.concatenate([cells[key][control] for key in judged]),
            )
            lines.append(
                f"- minus {control}: {everything[0]:+.4f} ± {everything[1]:.4f} over all trials; within 1 SE or above "
                f"in {len(judged) - len(below)}/{len(judged)} cells"
                + (f" (below: {'; '.join(below)})" if below else "")
            )
    lines += ["", "## Noise only, camera-like: candidate minus ECR uniform mean (needs >= 2 SE at high noise)", ""]
    for key in keys:
        if is_noise_only(key[0]) and key[1] == "camera-like":
            for candidate in ("ECR true", "ECR today"):
                if candidate in cells[key] and "ECR uniform mean" in cells[key]:
                    mean, error = paired_difference(cells[key][candidate], cells[key]["ECR uniform mean"])
                    verdict = "yes" if mean > 0 and mean >= 2 * error else "no"
                    lines.append(
                        f"- {key[0]}, sigma {key[2]:g}, {candidate}: {mean:+.2f} ± {error:.2f} "
                        f"({mean / max(error, 1e-12):.1f} SE): {verdict}"
                    )
    lines += ["", "## Estimated tau^2: median (25 %, 75 %) over the trials", ""]
    estimators = [method for method in ESTIMATED if any(row[3] == method and row[7] for row in rows)]
    lines += ["| case | sensor | sigma | " + " | ".join(estimators) + " |", "|---|---|---|" + "---|" * len(estimators)]
    tau_table = {(row[0], row[1], float(row[2]), row[3]): row[7] for row in rows if row[7]}
    for key in keys:
        texts = []
        for method in estimators:
            values = np.array([float(value) for value in tau_table.get((*key, method), "").split()])
            texts.append(
                f"{np.median(values):.3g} ({np.quantile(values, 0.25):.3g}, {np.quantile(values, 0.75):.3g})"
                if len(values)
                else ""
            )
        lines.append(f"| {key[0]} | {key[1]} | {key[2]:g} | " + " | ".join(texts) + " |")
    return "\n".join(lines) + "\n"


def _check_untracked(paths: list[Path]) -> None:
    """Refuse to overwrite a file that git tracks."""
    for path in paths:
        if not path.exists():
            continue
        tracked = subprocess.run(
            ["git", "-C", str(path.parent), "ls-files", "--error-unmatch", path.name], capture_output=True, check=False
        )
        if tracked.returncode == 0:
            raise SystemExit(f"--output: {path} is tracked by git; choose another folder")


def read_rows(path: Path) -> list:
    with path.open(newline="") as file:
        return [
            (row[0], row[1], float(row[2]), row[3], int(row[4]), int(row[5]), row[6], row[7])
            for row in list(csv.reader(file))[1:]
        ]


def read_learned_mask(path: Path) -> torch.Tensor:
    """A ``(LOCAL, LOCAL)`` ``.npy`` variance map, > 0 and finite everywhere, as ``(1, 1, LOCAL, LOCAL)`` float32."""
    mask = read_npy(path, "--learned-mask").astype(np.float64)
    if mask.shape != (LOCAL, LOCAL):
        raise ValueError(f"--learned-mask must be a ({LOCAL}, {LOCAL}) variance map, got shape {mask.shape}")
    if not (np.isfinite(mask).all() and (mask > 0).all()):
        raise ValueError(f"--learned-mask must be finite and > 0 at every pixel, {path} is not")
    return torch.from_numpy(mask).float()[None, None]


class _InProcess:
    """``ProcessPoolExecutor``'s ``submit`` run in this process (``--jobs 1``: nothing to pickle, easy to profile)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        return None

    def submit(self, function, *args) -> Future:
        future = Future()
        future.set_result(function(*args))
        return future


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("--trials", type=int, default=100, help="paired trials per cell (default 100)")
    parser.add_argument(
        "--cases",
        nargs="+",
        default=None,
        help=f"cases (default: {' '.join(CASES)}, --data's, {' '.join(LATER_CASES)})",
    )
    parser.add_argument("--sensors", nargs="+", choices=SENSORS, default=["camera-like", "lidar-like"])
    parser.add_argument(
        "--noise-only-sensors",
        nargs="+",
        choices=SENSORS,
        default=list(SENSORS),
        help="sensors of the noise-only cases",
    )
    parser.add_argument("--levels", nargs="+", type=float, default=None, help="mean noise sigmas (skip calibration)")
    parser.add_argument("--same-levels", nargs="*", type=float, default=[240.0, 480.0], help="extra levels, noise only")
    parser.add_argument("--calibration", type=Path, default=None, help="a calibration.json of an earlier run")
    parser.add_argument("--calibration-trials", type=int, default=32, help="trials per level of the calibration (32)")
    parser.add_argument(
        "--calibration-methods",
        nargs="+",
        choices=list(METHODS),
        default=list(CALIBRATION_METHODS),
        help="methods whose best sets L50 (default: every score of the table's columns, NCC and linear included)",
    )
    parser.add_argument(
        "--fractions", nargs="+", type=float, default=[0.25, 1.0], help="levels as fractions of L50 (0.25 1)"
    )
    parser.add_argument(
        "--no-clip", dest="clip", action="store_false", help="leave noisy grey levels unclipped (before issue 33)"
    )
    parser.add_argument(
        "--methods", nargs="+", choices=[*METHODS, "all"], default=list(DEFAULT_METHODS), help="methods, or 'all'"
    )
    parser.add_argument("--learned-mask", type=Path, default=None, help="(64, 64) .npy variance map for ECR learned")
    parser.add_argument("--data", type=Path, default=Path("/work/data/scene_change"), help="real pairs, if present")
    parser.add_argument(
        "--real-folders", choices=REAL_FOLDERS, default="all", help="all pair folders, or every other one per dataset"
    )
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (one torch thread each)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=Path("runs/yardstick_scene_change"), help="output folder")
    parser.add_argument("--report", action="store_true", help="only print the report of an existing --output")
    parser.add_argument("--calibrate-only", action="store_true", help="stop after writing calibration.json")
    args = parser.parse_args(argv)
    if args.trials < 2 or args.jobs < 1 or args.calibration_trials < 2:
        parser.error(f"--trials, --calibration-trials >= 2 and --jobs >= 1, got {args.trials}, {args.jobs}")
    if min(args.fractions) <= 0:
        parser.error(f"--fractions: expected fractions of L50 > 0, got {args.fractions}")
    methods = list(METHODS) if "all" in args.methods else list(dict.fromkeys(args.methods))
    results, calibration_path = args.output / "results.csv", args.output / "calibration.json"
    report_path, data_path = args.output / "report.md", args.output / "data.json"
    if args.report:
        if not results.exists():
            parser.error(f"--output: {results} does not exist; run without --report first")
        calibration = json.loads(calibration_path.read_text()) if calibration_path.exists() else []
        print(report(read_rows(results), calibration))
        return
    learned = None
    if "ECR learned" in methods:
        if args.learned_mask is None:
            parser.error("--methods: 'ECR learned' needs --learned-mask")
        try:
            learned = read_learned_mask(args.learned_mask)
        except (OSError, ValueError) as error:
            parser.error(str(error))
    data = args.data if args.data.is_dir() else None
    cases = args.cases or [*CASES, *real_cases(data), *LATER_CASES]
    for case in cases:
        try:
            parse_case(case)
            if real_name(case):
                if data is None:
                    raise ValueError(f"case {case!r} needs --data, and {args.data} is not a folder")
                pair_folders(data, real_name(case), args.real_folders)
        except ValueError as error:
            parser.error(f"--cases: {error}")
    _check_untracked([results, calibration_path, report_path, data_path])
    args.output.mkdir(parents=True, exist_ok=True)
    used = {
        case: [str(folder) for folder in pair_folders(data, real_name(case), args.real_folders)]
        for case in cases
        if real_name(case)
    }
    data_path.write_text(json.dumps(used, indent=1))
    start = time.perf_counter()
    units = [
        (case, sensor)
        for case in cases
        for sensor in (args.noise_only_sensors if is_noise_only(case) else args.sensors)
    ]
    case_seed = {case: args.seed * 1000 + index for index, case in enumerate(cases)}
    calibration = []
    with ProcessPoolExecutor(args.jobs) if args.jobs > 1 else _InProcess() as pool:
        if args.levels is None:
            known = {}
            if args.calibration is not None:
                # An entry calibrated on other methods or without clipping sets other levels: it is run again.
                known = {
                    (entry["case"], entry["sensor"]): entry
                    for entry in json.loads(args.calibration.read_text())
                    if entry.get("methods", list(INFORMATION_METHODS)) == list(args.calibration_methods)
                    and entry.get("clip", False) == args.clip
                }
            missing = [unit for unit in units if unit not in known]
            futures = [
                pool.submit(
                    calibrate,
                    case,
                    sensor,
                    args.calibration_trials,
                    case_seed[case] + 500,
                    data,
                    tuple(args.calibration_methods),
                    args.clip,
                )
                for case, sensor in missing
            ]
            for done, future in enumerate(futures, 1):
                entry = future.result()
                known[entry["case"], entry["sensor"]] = entry
                print(
                    f"[calibration {done}/{len(futures)}] {entry['case']} {entry['sensor']}: L50 {entry['L50']:g} "
                    f"({entry['bracketed']}), {time.perf_counter() - start:.0f} s",
                    file=sys.stderr,
                    flush=True,
                )
            calibration = [known[unit] for unit in units]
            calibration_path.write_text(json.dumps(calibration, indent=1))
        if args.calibrate_only:
            print(f"wrote {calibration_path}")
            return
        futures = []
        for case, sensor in units:
            if args.levels is not None:
                levels = list(args.levels)
            else:
                l50 = next(entry["L50"] for entry in calibration if (entry["case"], entry["sensor"]) == (case, sensor))
                levels = sorted(
                    {l50 if fraction == 1 else float(f"{l50 * fraction:.2g}") for fraction in args.fractions}
                )
                if is_noise_only(case):
                    levels = sorted(set(levels) | set(args.same_levels))
            futures.append(
                pool.submit(
                    run_cell,
                    case,
                    sensor,
                    levels,
                    args.trials,
                    case_seed[case],
                    data,
                    tuple(methods),
                    args.real_folders,
                    learned,
                    args.clip,
                )
            )
        rows = []
        for done, future in enumerate(futures, 1):
            rows += future.result()
            print(
                f"[{done}/{len(futures)}] {' '.join(units[done - 1])} done, {time.perf_counter() - start:.0f} s",
                file=sys.stderr,
                flush=True,
            )
    with results.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["case", "sensor", "mean_sigma", "method", "successes", "trials", "outcomes", "tau2"])
        writer.writerows(rows)
    text = report(rows, calibration)
    report_path.write_text(text)
    print(text)
    print(
        f"{len(units)} cases x sensors, {args.trials} trials, {time.perf_counter() - start:.0f} s "
        f"({args.jobs} jobs, one torch thread each); wrote {args.output}"
    )


if __name__ == "__main__":
    main()
