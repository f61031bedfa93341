"""Does the per-pixel variance pay where the scene changed? Localization success against controls, paired trials.

Each trial cuts a 64 x 64 captured image at a known shift within +-12 cells (yaw 0) of an 88 x 88 map window and
searches the 25 x 25 shifts with every method on the same noisy image (common random numbers: the same poses, scene
changes and standard-normal draws, scaled, for every method and noise level). Success: the best shift within one
cell of the truth on both axes.

Cases:

* ``same``: the captured image is the map itself (noise only, today's yardstick);
* ``<change>@<strength>``: the map window changed by :mod:`enmi_torch.data.scene_change` (``illumination``,
  ``shadows``, ``occluders``, ``tone``, ``resample_blur``, ``warp``, or ``mixed``: all of them) before the captured
  image is cut from it; maps are scikit-image's photographs of ``data_tools/yardstick.py`` (one drawn per trial);
* ``real:<case>/<dataset>``: real pairs from ``--data DIR`` (``DIR/<case>/<dataset>-<id>/reference.npy`` and
  ``captured.npy``, grey levels in [0, 255], co-registered; one pair of the dataset drawn per trial; ``real:<case>``:
  all its datasets), when the folder is there; ``data.json`` lists the pair folders each case drew from.

Sensors: ``camera-like`` (far rows ~100x noisier) and ``lidar-like`` (~100x at the corners), the profiles of
``data_tools/yardstick.py``, scaled so that the mean noise standard deviation is the level. Levels per case and sensor:
the hardest level where some information score (ECR true, ECR uniform, ENMI uniform, NMI) still succeeds half the time
(``L50``, from a calibration pass on trials of their own, recorded in ``calibration.json``) and ``L50 / 4``; the
noise-only case also at ``--same-levels``.

Methods (32 bins; the table :data:`METHODS` says which score with which variance): ECR with the true per-pixel
variance and today's ``tau^2``; ECR and ENMI with one uniform variance, the true map's mean times 1/16, 1/4, 1, 4, 16
(``uniform mean`` is x1, ``best uniform`` the best of the five per cell, an oracle); ENMI true; NMI; NCC; ECR true with
``model_variance`` 1024 and 4096; and ECR true with ``tau^2`` estimated from the data (prototypes in
``enmi_torch/_model_variance.py``):

* ``ECR est <first>``: one ``tau^2`` per captured image (REML) from the residuals at the best placement of a first
  pass (``cheap``: the two-stage search's 4-bin stage; ``uniform``; ``default``: today's surface; ``r2``: a second
  round; ``oracle``: at the true placement), then the surface rescored with it;
* ``ECR profile 6`` / ``3``: ``tau^2`` maximised per placement by profile likelihood on 6 or 3 planes;
* ``ECR per-bin``: one ``tau_j^2`` per reference bin;
* ``ECR local <kind>``: one ``tau_n^2`` per captured pixel from the residuals at the first pass's peak, smoothed
  (``fisher``: Fisher-weighted Gaussian moments, 3 px; ``smooth``, ``eb``, ``student``; ``i2``: means re-estimated;
  ``c8``: 8 candidate peaks chosen by likelihood; ``oracle``: at the true placement).

The default ``--methods`` are :data:`DEFAULT_METHODS` (the controls, the pooled and local estimates, the profile and
the oracles; ~13 minutes for 100 trials on 2 cores); ``--methods all`` runs every one.

Writes ``results.csv`` (outcomes per trial as bits, and the estimated ``tau^2`` per trial for the estimators),
``calibration.json``, ``data.json`` and ``report.md`` into ``--output`` (refusing files git tracks), and prints the
report.

    python data_tools/yardstick/scene_change.py --trials 12 --cases same tone@1 --output /tmp/sc   # a minute or two
    python data_tools/yardstick/scene_change.py --trials 100 --jobs 2                            # the full table
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import json
import math
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from enmi_torch import _model_variance as model_variance
from enmi_torch._files import read_npy
from enmi_torch.data.scene_change import CHANGES, scene_change
from enmi_torch.localization.surface import ecr_surface, enmi_surface, ncc_surface, nmi_surface


def _noise_only_yardstick():
    """Today's yardstick (profiles, maps, success rule), imported from its file: ``data_tools/yardstick.py``."""
    here = Path(__file__).resolve().parent
    for path in (here / "noise_only.py", here.parent / "yardstick.py"):
        if path.exists():
            spec = importlib.util.spec_from_file_location("_noise_only_yardstick", path)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            return module
    raise FileNotFoundError(f"today's yardstick not found beside {here} (noise_only.py or ../yardstick.py)")


NOISE_ONLY = _noise_only_yardstick()
LOCAL, RADIUS, BINS = NOISE_ONLY.LOCAL, NOISE_ONLY.RADIUS, NOISE_ONLY.BINS
SPAN = LOCAL + 2 * RADIUS
SENSORS = ("camera-like", "lidar-like")
KINDS = (*CHANGES, "mixed")
CASES = ("same", *(f"{kind}@{strength}" for kind in CHANGES for strength in (0.5, 1)), "mixed@0.25", "mixed@0.35")
GRID = (1 / 16, 1 / 4, 1.0, 4.0, 16.0)
CALIBRATION_LEVELS = (4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0, 1024.0, 2048.0)
CALIBRATION_METHODS = ("ECR true", "ECR uniform x1", "ENMI uniform x1", "NMI")
CHUNK = 25  # trials per surface call: memory stays small


class Context(NamedTuple):
    """One chunk of trials at one level: what every method sees."""

    local: torch.Tensor  # (T, 1, LOCAL, LOCAL) float32 noisy captured images
    window: torch.Tensor  # (T, 1, SPAN, SPAN) float32 map windows
    variance: torch.Tensor  # (1, 1, LOCAL, LOCAL) float32 true noise variance
    mean: float  # the true variance's mean
    truth: torch.Tensor  # (T, 2) true placement (row, col)


def _score(surface) -> tuple[torch.Tensor, None]:
    return surface.score, None


def _ecr(factor: float | None = None, tau2: float | None = None):
    """ECR with the true variance (``factor`` None) or the uniform ``mean * factor``; ``tau2`` its model variance."""

    def method(context: Context):
        variance = context.variance if factor is None else context.mean * factor
        return _score(ecr_surface(context.local, context.window, variance, bins=BINS, model_variance=tau2))

    return method


def _enmi(factor: float | None = None):
    def method(context: Context):
        variance = context.variance if factor is None else context.mean * factor
        return _score(enmi_surface(context.local, context.window, variance, bins=BINS))

    return method


def _estimated(**options):
    """ECR true with ``tau^2`` per captured image (``oracle=True``: estimated at the true placement)."""
    return lambda context: _estimated_call(context, options)


def _estimated_call(context: Context, options: dict):
    options = dict(options)
    placements = context.truth if options.pop("oracle", False) else None
    surface, tau2 = model_variance.ecr_estimated_surface(
        context.local, context.window, context.variance, bins=BINS, placements=placements, **options
    )
    return surface.score, tau2


def _profile(factors: tuple[float, ...]):
    def method(context: Context):
        surface, tau2 = model_variance.ecr_profile_surface(
            context.local, context.window, context.variance, bins=BINS, factors=factors
        )
        return surface.score, tau2

    return method


def _per_bin(context: Context):
    surface, tau2 = model_variance.ecr_bin_variance_surface(context.local, context.window, context.variance, bins=BINS)
    return surface.score, tau2


def _local(oracle: bool = False, **options):
    def method(context: Context):
        placements = context.truth if oracle else None
        surface, tau2 = model_variance.ecr_local_surface(
            context.local, context.window, context.variance, bins=BINS, placements=placements, **options
        )
        return surface.score, tau2

    return method


def _factor_name(factor: float) -> str:
    return f"x{factor:g}"


# The plumbing in one table: which score with which variance (the lead ports it to the score objects).
METHODS: dict[str, Callable[[Context], tuple[torch.Tensor, torch.Tensor | None]]] = {
    "ECR true": _ecr(),
    **{f"ECR uniform {_factor_name(factor)}": _ecr(factor) for factor in GRID},
    "ENMI true": _enmi(),
    **{f"ENMI uniform {_factor_name(factor)}": _enmi(factor) for factor in GRID},
    "NMI": lambda context: _score(nmi_surface(context.local, context.window, bins=BINS)),
    "NCC": lambda context: _score(ncc_surface(context.local, context.window)),
    "ECR tau 1024": _ecr(tau2=1024.0),
    "ECR tau 4096": _ecr(tau2=4096.0),
    "ECR est cheap": _estimated(first="cheap"),
    "ECR est cheap r2": _estimated(first="cheap", rounds=2),
    "ECR est uniform": _estimated(first="uniform"),
    "ECR est default": _estimated(first="default"),
    "ECR est oracle": _estimated(oracle=True),
    "ECR profile 6": _profile((1.0, 1 / 4, 1 / 16, 1 / 64, 1 / 256, 1 / 1024)),
    "ECR profile 3": _profile((1.0, 1 / 16, 1 / 256)),
    "ECR per-bin": _per_bin,
    "ECR local smooth": _local(kind="smooth", scale=3.0),
    "ECR local smooth r2": _local(kind="smooth", scale=3.0, rounds=2),
    "ECR local student": _local(kind="student", scale=4.0),
    "ECR local fisher": _local(kind="fisher", scale=3.0),
    "ECR local fisher i2": _local(kind="fisher", scale=3.0, iterations=2),
    "ECR local fisher s2": _local(kind="fisher", scale=2.0),
    "ECR local fisher s5": _local(kind="fisher", scale=5.0),
    "ECR local smooth i2": _local(kind="smooth", scale=3.0, iterations=2),
    "ECR local eb": _local(kind="eb", scale=3.0),
    "ECR local fisher c3": _local(kind="fisher", scale=3.0, candidates=3),
    "ECR local fisher c8 pooled": _local(kind="fisher", scale=3.0, candidates=8, select="pooled"),
    "ECR local fisher default": _local(kind="fisher", scale=3.0, first="default"),
    "ECR local fisher cheap8": _local(kind="fisher", scale=3.0, first="cheap8"),
    "ECR local fisher uniform": _local(kind="fisher", scale=3.0, first="uniform"),
    "ECR local fisher c8": _local(kind="fisher", scale=3.0, candidates=8),
    "ECR local fisher i2 c8": _local(kind="fisher", scale=3.0, iterations=2, candidates=8),
    "ECR local fisher c8 default": _local(kind="fisher", scale=3.0, candidates=8, first="default"),
    "ECR local fisher oracle": _local(oracle=True, kind="fisher", scale=3.0),
    "ECR local fisher i2 oracle": _local(oracle=True, kind="fisher", scale=3.0, iterations=2),
    "ECR local eb i2": _local(kind="eb", scale=3.0, iterations=2),
    "ECR local eb s5": _local(kind="eb", scale=5.0),
    "ECR local eb s2": _local(kind="eb", scale=2.0),
}
DEFAULT_METHODS = (
    "ECR true",
    *(f"ECR uniform {_factor_name(factor)}" for factor in GRID),
    "ENMI true",
    *(f"ENMI uniform {_factor_name(factor)}" for factor in GRID),
    "NMI",
    "NCC",
    "ECR tau 1024",
    "ECR tau 4096",
    "ECR est cheap",
    "ECR est oracle",
    "ECR profile 6",
    "ECR local fisher",
    "ECR local eb",
    "ECR local fisher c8",
    "ECR local fisher oracle",
)
# Columns of the report: the grids collapse into their mean and their best (picked per cell after the fact).
DERIVED = {"ECR uniform mean": "ECR uniform x1", "ENMI uniform mean": "ENMI uniform x1"}
BEST = {"ECR best uniform": "ECR uniform ", "ENMI best uniform": "ENMI uniform "}
CONTROLS = ("ECR uniform mean", "ECR best uniform", "ENMI best uniform", "NMI", "NCC")


class Trials(NamedTuple):
    """The trials of one case, before noise."""

    clean: torch.Tensor  # (T, 1, LOCAL, LOCAL) float64 noiseless captured images
    window: torch.Tensor  # (T, 1, SPAN, SPAN) float64 map windows
    truth: torch.Tensor  # (T, 2) int64
    draws: torch.Tensor  # (T, 1, LOCAL, LOCAL) float64 standard-normal draws


def parse_case(case: str) -> tuple[str, float]:
    """``(kind, strength)`` of a case name: ``same`` -> ``("same", 0)``, ``tone@0.5``, ``real:another-date``."""
    if case == "same" or case.startswith("real:"):
        return case, 0.0
    kind, _, strength = case.partition("@")
    if kind not in KINDS or not strength:
        raise ValueError(f"case must be 'same', 'real:<folder>' or '<change>@<strength>' with change in {KINDS}")
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


def pair_folders(data: Path, name: str) -> list[Path]:
    """The pair folders of ``name``: ``<case>`` (all of ``data/<case>/``) or ``<case>/<dataset>``."""
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
    if not folders:
        raise ValueError(f"--data: no pair folder for case 'real:{name}' under {data / case}")
    return folders


def real_pairs(data: Path, name: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """The ``(reference, captured)`` grey arrays of :func:`pair_folders`, those at least the window's size."""
    pairs = []
    for folder in pair_folders(data, name):
        reference = read_npy(folder / "reference.npy", "--data").astype(np.float64)
        captured = read_npy(folder / "captured.npy", "--data").astype(np.float64)
        if reference.ndim == 3:
            reference, captured = reference.mean(-1), captured.mean(-1)
        if reference.shape != captured.shape:
            raise ValueError(f"--data: {folder} holds reference {reference.shape} and captured {captured.shape}")
        if min(reference.shape) >= SPAN:
            pairs.append((reference, captured))
    if not pairs:
        raise ValueError(f"--data: no pair of at least {SPAN} x {SPAN} for case 'real:{name}'")
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


def make_trials(case: str, trials: int, seed: int, data: Path | None = None) -> Trials:
    """The trials of one case: poses, scene changes and noise draws, a function of ``(case, trials, seed)``."""
    kind, strength = parse_case(case)
    generator = torch.Generator().manual_seed(seed)
    if kind.startswith("real:"):
        sources = [(torch.from_numpy(r), torch.from_numpy(c)) for r, c in real_pairs(data, kind[5:])]
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
        if kind not in ("same",) and not kind.startswith("real:"):
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


def _contexts(trials: Trials, sensor: str, level: float):
    unit, valid = NOISE_ONLY.variance_profile(sensor)
    if not bool(valid.all()):
        raise ValueError(f"sensor {sensor!r} leaves cells out; the scene-change yardstick needs full images")
    variance = (level**2 * unit)[None, None]
    local = (trials.clean + trials.draws * variance.sqrt()).float()
    mean = float(variance.mean())
    for start in range(0, local.shape[0], CHUNK):
        part = slice(start, start + CHUNK)
        yield Context(local[part], trials.window[part].float(), variance.float(), mean, trials.truth[part])


def run_methods(trials: Trials, sensor: str, level: float, methods) -> dict[str, tuple[torch.Tensor, list]]:
    """Per method: success per trial (bool ``(T,)``) and the estimated ``tau^2`` per trial (empty when none)."""
    torch.set_num_threads(1)
    success = {method: [] for method in methods}
    tau2 = {method: [] for method in methods}
    for context in _contexts(trials, sensor, level):
        for method in methods:
            score, estimate = METHODS[method](context)
            success[method].append(NOISE_ONLY._outcomes(score, context.truth)[0])
            if estimate is not None:
                tau2[method] += [float(value) for value in estimate]
    return {method: (torch.cat(success[method]), tau2[method]) for method in methods}


def calibrate(case: str, sensor: str, trials: int, seed: int, data: Path | None) -> dict:
    """Success of :data:`CALIBRATION_METHODS` per level and ``L50``: the hardest level where the best reaches 1/2.

    ``L50`` interpolates the best rate linearly in ``log level`` between the last level at or above 1/2 and the next;
    when no level reaches 1/2 it is the lowest level, when all do the highest (``bracketed`` says which).
    """
    torch.set_num_threads(1)
    generated = make_trials(case, trials, seed, data)
    best = []
    for level in CALIBRATION_LEVELS:
        results = run_methods(generated, sensor, level, CALIBRATION_METHODS)
        best.append(max(float(outcome.double().mean()) for outcome, _ in results.values()))
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
    return {"case": case, "sensor": sensor, "L50": level, "bracketed": bracketed, "best_rates": best}


def run_cell(case, sensor, levels, trials, seed, data, methods) -> list:
    """Rows ``(case, sensor, level, method, successes, trials, outcomes, tau2s)`` of one case and sensor."""
    generated = make_trials(case, trials, seed, data)
    rows = []
    for level in levels:
        for method, (success, tau2) in run_methods(generated, sensor, level, methods).items():
            bits = "".join("1" if value else "0" for value in success.tolist())
            tau_text = " ".join(f"{value:.4g}" for value in tau2)
            rows.append((case, sensor, level, method, int(success.sum()), trials, bits, tau_text))
    return rows


def _bits(text: str) -> np.ndarray:
    return np.array([int(bit) for bit in text])


def _paired(first: np.ndarray, second: np.ndarray) -> tuple[float, float]:
    difference = first - second
    error = difference.std(ddof=1) / math.sqrt(len(difference)) if len(difference) > 1 else 0.0
    return float(difference.mean()), float(error)


def cell_outcomes(rows: list) -> dict:
    """``{(case, sensor, level): {method: outcomes}}`` with the derived columns (uniform mean, best uniform)."""
    cells: dict = {}
    for case, sensor, level, method, _, _, bits, _ in rows:
        cells.setdefault((case, sensor, float(level)), {})[method] = _bits(bits)
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


def _rate(bits: np.ndarray) -> str:
    rate = bits.mean()
    return f"{rate:.2f} ± {math.sqrt(rate * (1 - rate) / len(bits)):.2f}"


def report(rows: list, calibration: list, candidates: list[str]) -> str:
    """The markdown report: success tables, paired claims of each candidate against the controls, ``tau^2``."""
    cells = cell_outcomes(rows)
    keys = list(cells)
    shown = [
        method
        for method in (
            "ECR true",
            *candidates,
            "ECR uniform mean",
            "ECR best uniform",
            "ENMI true",
            "ENMI best uniform",
            "NMI",
            "NCC",
            "ECR tau 1024",
            "ECR tau 4096",
        )
        if any(method in cells[key] for key in keys)
    ]
    shown = list(dict.fromkeys(shown))
    lines = []
    if calibration:
        lines += ["## Calibration: L50 per case and sensor (best of " + ", ".join(CALIBRATION_METHODS) + ")", ""]
        lines += [
            "| case | sensor | L50 | bracketed | best rate per level (from 4, x2 each) |",
            "|---|---|---|---|---|",
        ]
        for entry in calibration:
            rates = " ".join(f"{rate:.2f}" for rate in entry["best_rates"])
            lines.append(f"| {entry['case']} | {entry['sensor']} | {entry['L50']:g} | {entry['bracketed']} | {rates} |")
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
    lines += ["", "## Pooled over all cells: successes (of trials)", ""]
    lines += ["| " + " | ".join(shown) + " |", "|" + "---|" * len(shown)]
    totals = [sum(int(cells[key][m].sum()) for key in keys if m in cells[key]) for m in shown]
    counts = [sum(len(cells[key][m]) for key in keys if m in cells[key]) for m in shown]
    lines.append("| " + " | ".join(f"{total} ({count})" for total, count in zip(totals, counts, strict=True)) + " |")
    lines += ["", "## Paired differences: cells where the candidate is more than 1 SE below a control", ""]
    lines += ["| candidate | " + " | ".join(CONTROLS) + " |", "|---|" + "---|" * len(CONTROLS)]
    failures_text = []
    for candidate in ["ECR true", *candidates]:
        if not any(candidate in cells[key] for key in keys):
            continue
        counts_text = []
        for control in CONTROLS:
            judged = [key for key in keys if candidate in cells[key] and control in cells[key]]
            failures = []
            for key in judged:
                mean, error = _paired(cells[key][candidate], cells[key][control])
                if mean < -error - 1e-12:
                    failures.append(f"{key[0]}/{key[1]}/{key[2]:g}: {mean:+.2f} ± {error:.2f}")
            counts_text.append(f"{len(judged) - len(failures)}/{len(judged)}")
            if failures:
                failures_text.append(f"- {candidate} vs {control}: " + "; ".join(failures))
        lines.append(f"| {candidate} | " + " | ".join(counts_text) + " |")
    lines += ["", "(within 1 SE or above / cells judged)", "", *failures_text]
    lines += ["", "## Noise only, camera-like: candidate minus ECR uniform mean (needs >= 2 SE at high noise)", ""]
    for key in keys:
        if key[0] == "same" and key[1] == "camera-like":
            for candidate in ["ECR true", *candidates]:
                if candidate in cells[key] and "ECR uniform mean" in cells[key]:
                    mean, error = _paired(cells[key][candidate], cells[key]["ECR uniform mean"])
                    verdict = "yes" if mean > 0 and mean >= 2 * error else "no"
                    lines.append(
                        f"- sigma {key[2]:g}, {candidate}: {mean:+.2f} ± {error:.2f} "
                        f"({mean / max(error, 1e-12):.1f} SE): {verdict}"
                    )
    lines += ["", "## Estimated tau^2: median (25 %, 75 %) over the trials", ""]
    estimators = sorted({row[3] for row in rows if row[7]})
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
    parser.add_argument("--cases", nargs="+", default=None, help=f"cases (default: {' '.join(CASES)} and --data's)")
    parser.add_argument("--sensors", nargs="+", choices=SENSORS, default=list(SENSORS))
    parser.add_argument("--levels", nargs="+", type=float, default=None, help="mean noise sigmas (skip calibration)")
    parser.add_argument("--same-levels", nargs="*", type=float, default=[240.0, 480.0], help="extra levels, noise only")
    parser.add_argument("--calibration", type=Path, default=None, help="a calibration.json of an earlier run")
    parser.add_argument("--calibration-trials", type=int, default=32, help="trials per level of the calibration (32)")
    parser.add_argument(
        "--methods", nargs="+", choices=[*METHODS, "all"], default=list(DEFAULT_METHODS), help="methods, or 'all'"
    )
    parser.add_argument("--data", type=Path, default=Path("/work/data/scene_change"), help="real pairs, if present")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (one torch thread each)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=Path("runs/yardstick_scene_change"), help="output folder")
    parser.add_argument("--report", action="store_true", help="only print the report of an existing --output")
    parser.add_argument("--calibrate-only", action="store_true", help="stop after writing calibration.json")
    args = parser.parse_args(argv)
    if args.trials < 2 or args.jobs < 1 or args.calibration_trials < 2:
        parser.error(f"--trials, --calibration-trials >= 2 and --jobs >= 1, got {args.trials}, {args.jobs}")
    candidates = [
        method for method in METHODS if method.startswith(("ECR est", "ECR profile", "ECR per-bin", "ECR local"))
    ]
    results, tau_path = args.output / "results.csv", args.output / "tau.csv"
    calibration_path, report_path = args.output / "calibration.json", args.output / "report.md"
    if args.report:
        if not results.exists():
            parser.error(f"--output: {results} does not exist; run without --report first")
        calibration = json.loads(calibration_path.read_text()) if calibration_path.exists() else []
        print(report(read_rows(results), calibration, candidates))
        return
    data = args.data if args.data.is_dir() else None
    cases = args.cases or [*CASES, *real_cases(data)]
    for case in cases:
        try:
            parse_case(case)
            if case.startswith("real:"):
                if data is None:
                    raise ValueError(f"case {case!r} needs --data, and {args.data} is not a folder")
                pair_folders(data, case[5:])
        except ValueError as error:
            parser.error(f"--cases: {error}")
    data_path = args.output / "data.json"
    _check_untracked([results, tau_path, calibration_path, report_path, data_path])
    args.output.mkdir(parents=True, exist_ok=True)
    used = {
        case: [str(folder) for folder in pair_folders(data, case[5:])] for case in cases if case.startswith("real:")
    }
    data_path.write_text(json.dumps(used, indent=1))
    start = time.perf_counter()
    units = [(case, sensor) for case in cases for sensor in args.sensors]
    case_seed = {case: args.seed * 1000 + index for index, case in enumerate(cases)}
    calibration = []
    with ProcessPoolExecutor(args.jobs) if args.jobs > 1 else _InProcess() as pool:
        if args.levels is None:
            known = {}
            if args.calibration is not None:
                known = {(entry["case"], entry["sensor"]): entry for entry in json.loads(args.calibration.read_text())}
            missing = [unit for unit in units if unit not in known]
            futures = [
                pool.submit(calibrate, case, sensor, args.calibration_trials, case_seed[case] + 500, data)
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
                levels = [float(f"{l50 / 4:.2g}"), l50]
            if case == "same":
                levels = sorted(set(levels) | set(args.same_levels))
            futures.append(
                pool.submit(run_cell, case, sensor, levels, args.trials, case_seed[case], data, tuple(args.methods))
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
    text = report(rows, calibration, candidates)
    report_path.write_text(text)
    print(text)
    print(
        f"{len(units)} cases x sensors, {args.trials} trials, {time.perf_counter() - start:.0f} s "
        f"({args.jobs} jobs, one torch thread each); wrote {args.output}"
    )


if __name__ == "__main__":
    main()
