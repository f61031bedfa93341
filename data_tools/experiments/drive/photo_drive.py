"""Track drives over real photographs taken on two dates: the map from one, the frames from the other.

The pairs are the co-registered folders written by ``data_tools.experiments.yardstick.prepare_scene_change``
(``reference.npy``, the older date, is the map; ``captured.npy``, the other date, is what the vehicle sees), one map
cell per pixel. Each drive goes round a loop of ``--frames`` frames (radius ``--radius`` cells about the map's centre,
yaw 0); each frame is the 64 x 64 cut of the other date's photograph centred on the true cell, plus camera-like noise
whose standard deviation grows tenfold from the near (bottom) row to the far (top) row, so the far rows are 100 times
noisier in variance; its mean over the rows is ``--sigma`` grey levels. The odometry over-reads each move by 6 % and
adds white noise of 0.3 cells. The filter runs as README shows it (``Tracker(map, shifts=8, yaw_bins=3,
settings=TrackerSettings(motion_noise=(0.5, 0.5, 0.3)))``, no calibration); per-frame argmax searches the same window
around the previous estimate moved by the odometry and takes the best candidate. ``--oracle`` adds a reference that no
tracker can run, oracle gating: each frame is searched in the window centred on the truth, its best candidate taken
where it is within one cell of the truth, the odometry dead-reckoned through the other frames. It measures how much of a
drive the frames and the odometry leave to be lost even by a filter that never takes a wrong match. ``--temperatures
auto 5 10 30`` adds the filter with hand-set temperatures (``Tracker(..., settings=TrackerSettings(temperature=T))``)
beside README's automatic one: a grid of controls, a row "filter, temperature T" each; the best of them, chosen on these
same drives, is what tuning the temperature could reach.

Methods: ECR with the true per-row variance and with a uniform variance (``--uniform-scales`` times the true map's
mean: the grid of controls), NMI, NCC. ECR runs as each of ``--variants``
(:mod:`~data_tools.experiments.drive.variants`: ``binned``, the tracker's default,
``ECR(response="binned", misfit="correlated")`` per frame; ``held``, ``ECR()`` with its noise model held from a frame
it trusts; ``per_frame``, ``ECR()`` re-estimated every frame), a row each; ``--misfit`` gives every variant that misfit.
"Within 1 cell": on both axes; "lost": more than 4 cells from the truth; "covers": the filter's 95 % ellipse holds the
truth; "raised": drives that ended in an exception. A second table pairs each row with the first on the same drives;
the last line is JSON with every drive's values, pair by pair and seed by seed.

    python -m data_tools.experiments.yardstick.prepare_scene_change --dataset levir-cd --source DIR \
        --out runs/pairs --correct
    python -m data_tools.experiments.drive.photo_drive --pairs runs/pairs --seeds 0 1 2
    python -m data_tools.experiments.drive.photo_drive --pairs runs/pairs --seeds 0 1 2 --methods ecr_true \
        --variants held per_frame binned --oracle
    python -m data_tools.experiments.drive.photo_drive --pairs runs/pairs --seeds 0 1 2 --methods ecr_true ncc nmi \
        --oracle
    python -m data_tools.experiments.drive.photo_drive --pairs runs/pairs --seeds 0 1 2 --methods ecr_true \
        --temperatures auto 10
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from data_tools.experiments.drive.variants import (
    DEFAULT_VARIANT,
    VARIANT_LABELS,
    add_variant_options,
    mean_and_error,
    paired_rows,
    variant_score,
)
from enmi_torch import ECR, NCC, NMI, localize
from enmi_torch.localization import NoCandidateError
from enmi_torch.tracking import CHI2_95_2D, Tracker, TrackerSettings
from enmi_torch.tracking.belief import check_mismatch_probability

FRAME = 64
SHIFTS = 8
YAWS = [-1.0, 0.0, 1.0]  # the filter's yaw bins
OVER_READ = 1.06
ODOMETRY_NOISE = 0.3
SETTINGS = {"shifts": SHIFTS, "yaw_bins": 3}  # README's Tracker, with motion_noise=(0.5, 0.5, 0.3)


def load_pairs(root: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``(name, map, other date)`` of every pair folder under ``root`` (folders holding ``reference.npy``)."""
    pairs = []
    for reference_file in sorted(root.rglob("reference.npy")):
        folder = reference_file.parent
        reference = np.load(reference_file).astype(np.float64)
        captured = np.load(folder / "captured.npy").astype(np.float64)
        if reference.shape != captured.shape:
            raise ValueError(f"{folder}: reference {reference.shape} and captured {captured.shape} differ in shape")
        pairs.append((folder.name, reference, captured))
    return pairs


def loop(shape: tuple[int, int], frames: int, radius: float) -> torch.Tensor:
    """``(frames, 3)`` poses ``(x, y, 0)`` on whole cells round a circle about the map's centre."""
    angle = torch.linspace(0, 2 * math.pi, frames + 1, dtype=torch.float64)[:-1]
    x = (shape[1] - 1) / 2 + radius * angle.cos()
    y = (shape[0] - 1) / 2 + radius * angle.sin()
    return torch.stack([x.round(), y.round(), torch.zeros_like(x)], 1)


def row_sigma(mean_sigma: float) -> torch.Tensor:
    """``(FRAME,)`` noise std per row: tenfold from the bottom (near) to the top (far) row, mean ``mean_sigma``."""
    growth = 10.0 ** torch.linspace(1, 0, FRAME, dtype=torch.float64)  # row 0 (far) the noisiest
    return growth * (mean_sigma / float(growth.mean()))


def cut(image: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """The ``(1, 1, FRAME, FRAME)`` frame whose centre pixel ``(FRAME // 2, FRAME // 2)`` lies on the pose's cell."""
    x, y = int(pose[0]), int(pose[1])
    return image[None, None, y - FRAME // 2 : y + FRAME // 2, x - FRAME // 2 : x + FRAME // 2]


class PhotoDrive:
    """One drive: the truth, the noisy frames, their variance and the odometry."""

    def __init__(self, reference: np.ndarray, captured: np.ndarray, seed: int, args) -> None:
        generator = torch.Generator().manual_seed(seed)
        self.map = torch.from_numpy(reference)[None, None]
        other = torch.from_numpy(captured)
        self.truth = loop(reference.shape, args.frames, args.radius)
        sigma = row_sigma(args.sigma)
        self.variance = sigma.square()[:, None].expand(FRAME, FRAME)[None, None].contiguous()
        noise = torch.randn(len(self.truth), 1, FRAME, FRAME, generator=generator, dtype=torch.float64)
        self.frames = torch.cat([cut(other, pose) for pose in self.truth]) + noise * sigma[:, None]
        moves = self.truth[1:, :2] - self.truth[:-1, :2]
        odometry = moves * OVER_READ + ODOMETRY_NOISE * torch.randn(moves.shape, generator=generator).double()
        self.odometry = torch.cat([torch.zeros(1, 3), torch.cat([odometry, torch.zeros(len(moves), 1)], 1)]).double()


METHODS = {
    "ecr_true": ("ECR, true variance", ECR, "true"),
    "ecr_uniform": ("ECR, uniform variance", ECR, "uniform"),
    "nmi": ("NMI", NMI, None),
    "ncc": ("NCC", NCC, None),
}


def variance_of(drive: PhotoDrive, kind: str | None, uniform_scale: float) -> torch.Tensor | None:
    if kind is None:
        return None
    if kind == "uniform":
        return torch.full_like(drive.variance, uniform_scale * float(drive.variance.mean()))
    return drive.variance


def method_score(method: str, variant: str = DEFAULT_VARIANT, misfit: str | None = None):
    """A method's score (ECR's of the ``variant``, with ``misfit`` where given), variance kind and noise model."""
    _, family, kind = METHODS[method]
    if family is not ECR:
        return family(), kind, "per_frame"
    score, noise_model = variant_score(variant, misfit=misfit)
    return score, kind, noise_model


def run_filter(
    drive: PhotoDrive,
    method: str,
    uniform_scale: float = 1.0,
    misfit: str | None = None,
    mismatch_probability: float = 0.0,
    temperature: float | str = "auto",
    variant: str = DEFAULT_VARIANT,
) -> dict:
    score, kind, noise_model = method_score(method, variant, misfit)
    variance = variance_of(drive, kind, uniform_scale)
    variance = None if variance is None else variance.float()
    settings = TrackerSettings(
        motion_noise=(0.5, 0.5, 0.3),
        mismatch_probability=mismatch_probability,
        temperature=temperature,
        noise_model=noise_model,
    )
    tracker = Tracker(drive.map.float(), score=score, settings=settings, **SETTINGS)
    tracker.start(drive.truth[:1], std=(2.0, 2.0, 1.0))
    poses, covariances = [drive.truth[0]], [torch.zeros(3, 3, dtype=torch.float64)]
    for index in range(1, len(drive.truth)):
        output = tracker(drive.frames[index : index + 1].float(), drive.odometry[index : index + 1], variance)
        poses.append(output.pose[0].double())
        covariances.append(output.covariance[0].double())
    return {"pose": torch.stack(poses), "covariance": torch.stack(covariances)}


def best_match(drive: PhotoDrive, index: int, center: tuple[int, int], score, variance) -> torch.Tensor | None:
    """``(3,)`` pose of frame ``index``'s best candidate in the window about ``center`` (row, col); ``None`` if none."""
    frame = drive.frames[index : index + 1].float()
    try:
        around = (center[1], center[0])
        found = localize(frame, drive.map.float(), variance, score=score, shifts=SHIFTS, around=around, yaws=YAWS)
    except NoCandidateError:
        return None
    return found.pose[0].double()


def run_argmax(
    drive: PhotoDrive,
    method: str,
    uniform_scale: float = 1.0,
    misfit: str | None = None,
    variant: str = DEFAULT_VARIANT,
) -> dict:
    score, kind, _ = method_score(method, variant, misfit)
    variance = variance_of(drive, kind, uniform_scale)
    poses = [drive.truth[0]]
    for index in range(1, len(drive.truth)):
        guess = poses[-1].clone()
        guess[:2] += drive.odometry[index, :2]
        found = best_match(drive, index, (round(float(guess[1])), round(float(guess[0]))), score, variance)
        poses.append(guess if found is None else found)
    return {"pose": torch.stack(poses), "covariance": None}


def run_oracle_gating(
    drive: PhotoDrive,
    method: str,
    uniform_scale: float = 1.0,
    misfit: str | None = None,
    variant: str = DEFAULT_VARIANT,
) -> dict:
    """A reference, not a method: dead reckoning that is told which frames' best match is right.

    Each frame is searched in the filter's window (``SHIFTS`` cells, ``YAWS``) centred on its true cell. Where the
    best candidate is within one cell of the truth on both axes it is taken; elsewhere the pose is the last one moved
    by the odometry. No tracker knows which matches are right, so this shows how much of a drive the frames and the
    odometry leave to be lost by a filter that never takes a wrong match. It is not a strict bound: a filter may
    also estimate the odometry's bias, or use a match that is off by more than one cell. ``"right"``: ``(frames,)``
    bool, the frames whose best match is right (the first, the start, counts as right).
    """
    score, kind, _ = method_score(method, variant, misfit)
    variance = variance_of(drive, kind, uniform_scale)
    poses, right = [drive.truth[0]], [True]
    for index in range(1, len(drive.truth)):
        truth = drive.truth[index]
        found = best_match(drive, index, (int(truth[1]), int(truth[0])), score, variance)
        right.append(found is not None and bool((found[:2] - truth[:2]).abs().max() <= 1))
        if right[-1]:
            poses.append(found)
        else:
            guess = poses[-1].clone()
            guess[:2] += drive.odometry[index, :2]
            poses.append(guess)
    return {"pose": torch.stack(poses), "covariance": None, "right": torch.tensor(right)}


ESTIMATORS = {"per-frame argmax": run_argmax, "oracle gating": run_oracle_gating}  # beside the filter rows


def parse_temperature(text: str) -> float | str:
    """A filter temperature from the command line: ``"auto"`` or a finite number > 0; else a ValueError."""
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"--temperatures must be 'auto' or finite numbers > 0, got {text!r}")
    return value


def temperature_text(temperature: float | str) -> str:
    """``"auto"`` or the number, as the tables print a temperature."""
    return temperature if temperature == "auto" else f"{temperature:g}"


def filter_name(temperature: float | str) -> str:
    """The estimator's name of the filter at ``temperature``: ``"filter"`` for README's ``"auto"``."""
    return "filter" if temperature == "auto" else f"filter, temperature {temperature_text(temperature)}"


def measures(truth: torch.Tensor, result: dict) -> dict:
    difference = result["pose"][1:, :2] - truth[1:, :2]
    row = {
        "within 1 cell": float((difference.abs().amax(1) <= 1).double().mean()),
        "lost": float((difference.norm(dim=1) > 4).double().mean()),
    }
    if result["covariance"] is not None:
        column = difference[..., None]
        distance = (column.transpose(1, 2) @ torch.linalg.solve(result["covariance"][1:, :2, :2], column)).flatten()
        row["covers"] = float((distance <= CHI2_95_2D).double().mean())
    return row


def split_by_match(truth: torch.Tensor, result: dict, right: torch.Tensor) -> dict:
    """``measures`` of ``result`` over the frames whose best match is right and over the others (NaN where none)."""
    split = {}
    for part, frames in (("right", right[1:]), ("wrong", ~right[1:])):
        chosen = frames.nonzero()[:, 0] + 1
        row = {"frames": len(chosen), "within 1 cell": math.nan, "lost": math.nan}
        if len(chosen):
            picked = {"pose": torch.cat([result["pose"][:1], result["pose"][chosen]]), "covariance": None}
            row.update(measures(torch.cat([truth[:1], truth[chosen]]), picked))
        split[part] = row
    return split


def split_rows(splits: dict[str, dict[str, dict[str, list[float]]]], estimator: str = "filter") -> list[str]:
    """The filter (``estimator``) over the frames whose best match is right and over the others: frames, mean ± SE."""
    if not splits:
        return []
    lines = [
        f"\nThe {estimator} over the frames whose best match about the truth is right (oracle gating's) and over the "
        "others:\n",
        "| method | frames right | there: within 1 cell | lost | frames wrong | there: within 1 cell | lost |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for label, parts in splits.items():
        cells = []
        for part in ("right", "wrong"):
            values = parts[part]
            cells.append(str(int(sum(values["frames"]))))
            cells += [
                mean_and_error([v for v in values[measure] if math.isfinite(v)])
                for measure in ("within 1 cell", "lost")
            ]
        lines.append(f"| {label} | {' | '.join(cells)} |")
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--pairs", type=Path, required=True, help="folder of prepare_scene_change.py's pair folders")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="a drive per seed and pair")
    parser.add_argument("--frames", type=int, default=170, help="frames per loop")
    parser.add_argument("--radius", type=float, default=60.0, help="the loop's radius in cells")
    parser.add_argument("--sigma", type=float, default=90.0, help="the frames' noise std, mean over the rows")
    parser.add_argument("--methods", nargs="+", choices=list(METHODS), default=list(METHODS))
    add_variant_options(parser)
    parser.add_argument(
        "--uniform-scales",
        type=float,
        nargs="+",
        default=[1.0],
        help="the uniform controls: factors on the true variance's mean",
    )
    parser.add_argument(
        "--mismatch-probability",
        type=float,
        default=0.0,
        help="the filter's chance that a frame matched some other place (Tracker's mismatch_probability)",
    )
    parser.add_argument(
        "--temperatures",
        nargs="+",
        default=["auto"],
        help="the filter's temperatures: 'auto' (README's) and hand-set numbers > 0, a filter row each",
    )
    parser.add_argument(
        "--oracle",
        action="store_true",
        help="also the oracle gating reference: dead reckoning told which frames' best match is right; the first "
        "--temperatures filter is split by those frames",
    )
    args = parser.parse_args(argv)
    if args.frames < 2:
        parser.error(f"--frames must be an int >= 2, got {args.frames}")
    for name, value in (
        ("--radius", args.radius),
        ("--sigma", args.sigma),
        *(("--uniform-scales", scale) for scale in args.uniform_scales),
    ):
        if not (math.isfinite(value) and value > 0):
            parser.error(f"{name} must be finite numbers > 0, got {value}")
    try:
        check_mismatch_probability(args.mismatch_probability)  # the tracker's own bound
    except ValueError:
        parser.error(f"--mismatch-probability must be in [0, 1), got {args.mismatch_probability}")
    try:
        temperatures = list(dict.fromkeys(parse_temperature(text) for text in args.temperatures))
    except ValueError as error:
        parser.error(str(error))
    if not args.pairs.is_dir():
        parser.error(f"--pairs: {args.pairs} is not a folder")
    try:
        pairs = load_pairs(args.pairs)
    except ValueError as error:
        parser.error(f"--pairs: {error}")
    if not pairs:
        parser.error(f"--pairs: no reference.npy under {args.pairs}")
    margin = args.radius + FRAME // 2 + SHIFTS + 1
    small = [name for name, reference, _ in pairs if min(reference.shape) < 2 * margin]
    if small:
        parser.error(f"--radius {args.radius}: the loop and its frames leave the map of {small}; lower --radius")
    torch.set_num_threads(1)
    rows: dict[str, dict[str, list[float]]] = {}
    raised: dict[str, int] = {}
    splits: dict[str, dict[str, dict[str, list[float]]]] = {}
    filters = {filter_name(temperature): temperature for temperature in temperatures}
    split_filter = next(iter(filters))  # the filter that oracle gating's right and wrong frames split
    estimators = [*filters, "per-frame argmax", *(["oracle gating"] if args.oracle else [])]
    variants = list(dict.fromkeys(args.variants))
    runs = [
        (method, scale, variant)
        for method in args.methods
        for scale in (args.uniform_scales if method == "ecr_uniform" else [1.0])
        for variant in (variants if METHODS[method][1] is ECR else [DEFAULT_VARIANT])
    ]
    start = time.perf_counter()
    for name, reference, captured in pairs:
        for seed in args.seeds:
            drive = PhotoDrive(reference, captured, seed, args)
            searched = {}  # per-frame searches of one score run once (a held model is the filter's only)
            for method, scale, variant in runs:
                label = METHODS[method][0] + (
                    f" x {scale:g}" if method == "ecr_uniform" and len(args.uniform_scales) > 1 else ""
                )
                if METHODS[method][1] is ECR and len(variants) > 1:
                    label += f", {VARIANT_LABELS[variant]}"
                score = method_score(method, variant, args.misfit)[0]
                results = {}
                for estimator in estimators:
                    run = run_filter if estimator in filters else ESTIMATORS[estimator]
                    key = f"{label} | {estimator}"
                    options = (
                        {"mismatch_probability": args.mismatch_probability, "temperature": filters[estimator]}
                        if estimator in filters
                        else {}
                    )
                    try:
                        if estimator in filters:
                            result = run(drive, method, scale, args.misfit, variant=variant, **options)
                        else:
                            done = (estimator, method, scale, score)
                            if done not in searched:
                                searched[done] = run(drive, method, scale, args.misfit, variant=variant)
                            result = searched[done]
                        results[estimator] = result
                    except Exception as error:  # a drive that raises is a result, reported as such
                        print(f"{name} seed {seed} {key}: raised {type(error).__name__}: {error}", flush=True)
                        raised[key] = raised.get(key, 0) + 1
                        continue
                    for measure, value in measures(drive.truth, result).items():
                        rows.setdefault(key, {}).setdefault(measure, []).append(value)
                if split_filter in results and "oracle gating" in results:
                    split = split_by_match(drive.truth, results[split_filter], results["oracle gating"]["right"])
                    for part, values in split.items():
                        for measure, value in values.items():
                            splits.setdefault(label, {}).setdefault(part, {}).setdefault(measure, []).append(value)
                print(f"{name} seed {seed} {label}: {time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)
    drives = len(pairs) * len(args.seeds)
    print(
        f"\n{len(pairs)} pairs x {len(args.seeds)} seeds = {drives} drives of {args.frames} frames, loop radius "
        f"{args.radius:g} cells, noise std {args.sigma:g} (mean over rows, far rows 10x the near ones), ECR "
        f"{', '.join(VARIANT_LABELS[variant] for variant in variants)}, ECR's misfit "
        f"{args.misfit or 'as each variant'}, mismatch probability {args.mismatch_probability:g}, filter temperature "
        f"{', '.join(map(temperature_text, temperatures))}; mean ± SE over the drives\n"
    )
    print("| method | estimator | within 1 cell | lost (> 4 cells) | 95 % ellipse covers | raised |")
    print("| --- | --- | --- | --- | --- | --- |")
    for key in dict.fromkeys([*rows, *raised]):
        values = rows.get(key, {})
        cells = [mean_and_error(values.get(measure, [])) for measure in ("within 1 cell", "lost", "covers")]
        print(f"| {key} | {' | '.join(cells)} | {raised.get(key, 0)} |")
    print("\n".join(paired_rows(rows, drives, ("within 1 cell", "lost", "covers"))))
    print("\n".join(split_rows(splits, split_filter)))
    per_drive = {
        key: {measure: [round(value, 6) for value in values] for measure, values in row.items()}
        for key, row in rows.items()
    }
    summary = {
        "pairs": [name for name, _, _ in pairs],
        "seeds": args.seeds,
        "variants": variants,
        "misfit": args.misfit,
        "mismatch probability": args.mismatch_probability,
        "temperatures": temperatures,
        "drives": per_drive,
    }
    if splits:
        summary["filter by match"] = splits
        summary["filter split by match"] = split_filter
    print(json.dumps({**summary, "seconds": round(time.perf_counter() - start)}))


if __name__ == "__main__":
    main()
