"""Benchmark of ``enmi-fit-mask``: fitting 2,000 pairs of 128 x 128, before and after keeping the pairs in memory.

    python -m data_tools.benchmarks.bench_fit_mask              # 3 interleaved rounds, about 2 minutes on 2 cores
    python -m data_tools.benchmarks.bench_fit_mask --rounds 1 --pairs 500 --epochs 4

Runs the default configuration (configs/fit_mask.yaml) in this process, logging to a temporary folder, in two ways:

- before: the pairs drawn again whenever they are read (``--data.keep_pairs false``, every epoch), lane markings
  painted over the whole patch width, and every validation's localization dashboard scoring all its methods (the
  earlier ``_paint_marking``, kept below as the reference, and ``MaskFitModule._fixed`` scoring every time);
- after: the default, pairs generated once in ``setup()`` and kept, markings painted on the columns they touch, and
  the methods that do not depend on the mask (true map, NMI, NCC) scored at the first validation only.

It also checks that the summaries' dashboard values (the last validation's localization shares and margins, the
mask errors) are equal both ways.

The two alternate within each round (the order swaps from round to round); the script prints each fit as it ends,
the median of the per-round ratios before / after of the whole fit (data set-up, statistics pass, epochs,
validations) and of its parts: the training epochs (validations left out), and the rest (set-up, the statistics
pass and the validations: the dashboard's whole-image localization searches), and whether the two learned masks
are identical (bit for bit) in every round. Wall times swing with the machine's other work; the CPU time of the
process (the fit with its command line parsing and outputs, one torch thread: nothing spins) is the steadier
measure on a shared machine.
"""

from __future__ import annotations

import argparse
import io
import logging
import math
import os
import statistics
import tempfile
import time
from contextlib import contextmanager, redirect_stdout

import numpy as np
import torch

from enmi_torch.data import gravel_texture, synthetic
from enmi_torch.training.fit_mask import fit_mask
from enmi_torch.training.mask_module import MaskFitModule
from enmi_torch.variance import LearnedVariance

TARGET_SECONDS = 120.0
DASHBOARD = ("localization", "localization_z", "errors")  # the last validation's localization and the mask errors


def paint_marking_whole_width(patch: np.ndarray, rng: np.random.Generator, rows: np.ndarray, cols: np.ndarray) -> None:
    """The earlier ``synthetic._paint_marking``: coverage computed over every column of the patch."""
    height, width = patch.shape
    angle = math.radians(rng.uniform(-12.0, 12.0))
    column = rng.uniform(0.1, 0.9) * width
    half_width = rng.uniform(1.0, 3.5)
    across = (cols - column) * math.cos(angle) - (rows - height / 2) * math.sin(angle)
    along = (cols - column) * math.sin(angle) + (rows - height / 2) * math.cos(angle)
    coverage = np.clip(half_width + 0.5 - np.abs(across), 0.0, 1.0)
    if rng.random() < 0.5:
        period = rng.uniform(0.3, 0.6) * height
        dash = rng.uniform(0.4, 0.7) * period
        coverage = coverage * (np.mod(along + rng.uniform(0, period), period) < dash)
    paint = rng.uniform(200.0, 245.0)
    patch += coverage * (paint - patch)


def score_every_time(self, key, compute):
    """The earlier dashboard: the methods that do not depend on the mask scored again at every validation."""
    return compute()


@contextmanager
def before_change():
    """The earlier painting and dashboard, for the ``before`` runs."""
    painting, fixed = synthetic._paint_marking, MaskFitModule._fixed
    synthetic._paint_marking, MaskFitModule._fixed = paint_marking_whole_width, score_every_time
    try:
        yield
    finally:
        synthetic._paint_marking, MaskFitModule._fixed = painting, fixed


def run_fit(args: argparse.Namespace, keep_pairs: bool) -> tuple[dict, torch.Tensor]:
    """One default fit; returns its summary and the learned variance map."""
    with tempfile.TemporaryDirectory() as folder, redirect_stdout(io.StringIO()):  # the command's own summary
        summary = fit_mask(
            [
                *("--trainer.logger.init_args.save_dir", folder, "--trainer.enable_progress_bar", "false"),
                *("--data.train_pairs", str(args.pairs), "--data.size", str(args.size)),
                *("--data.batch_size", str(args.batch_size), "--trainer.max_epochs", str(args.epochs)),
                *("--trainer.check_val_every_n_epoch", str(max(1, args.epochs // 2))),
                *("--torch_threads", str(args.torch_threads), "--data.keep_pairs", str(keep_pairs).lower()),
            ]
        )
        mask = LearnedVariance.load(summary["files"]["pt"]).variance_map()
    return summary, mask


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=int, default=2000)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds of one fit each way")
    parser.add_argument("--torch-threads", type=int, default=1, help="as configs/fit_mask.yaml (default 1)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.torch_threads)
    print(
        f"fit_mask benchmark: {args.pairs} pairs of {args.size}x{args.size}, {args.epochs} epochs, "
        f"batch {args.batch_size}, {args.rounds} rounds; torch {torch.__version__}, {torch.get_num_threads()} "
        f"threads, {os.cpu_count()} CPUs, load average {' '.join(f'{load:.2f}' for load in os.getloadavg())}",
        flush=True,
    )
    gravel_texture()  # read once before the clock starts, for both ways
    for name in ("lightning.pytorch", "lightning.fabric"):  # progress lines, not Lightning's notices
        logging.getLogger(name).setLevel(logging.WARNING)
    parts = (
        "whole fit",
        "training epochs (validation left out)",
        "the rest (set-up, statistics pass, validations)",
        "CPU time of the process",
    )
    seconds: dict[str, dict[str, list[float]]] = {way: {part: [] for part in parts} for way in ("before", "after")}
    ratios: dict[str, list[float]] = {part: [] for part in parts}
    identical, dashboards, largest = [], [], 0.0
    for round_index in range(args.rounds):
        order = ("before", "after") if round_index % 2 == 0 else ("after", "before")
        masks, summaries = {}, {}
        for way in order:
            print(f"round {round_index + 1}/{args.rounds}: {way} ...", end=" ", flush=True)
            start, cpu_start = time.perf_counter(), time.process_time()
            if way == "before":
                with before_change():
                    summary, masks[way] = run_fit(args, keep_pairs=False)
            else:
                summary, masks[way] = run_fit(args, keep_pairs=True)
            summaries[way] = summary
            training = sum(summary["train_epoch_seconds"])  # the epochs' training time, validations left out
            cpu = time.process_time() - cpu_start
            times = (summary["seconds"], training, summary["seconds"] - training, cpu)
            for part, value in zip(parts, times, strict=True):
                seconds[way][part].append(value)
            print(
                f"fit {times[0]:.1f} s (training epochs {times[1]:.1f} s, set-up, statistics and validations "
                f"{times[2]:.1f} s; {time.perf_counter() - start:.1f} s with outputs, CPU {cpu:.1f} s; "
                f"load average {os.getloadavg()[0]:.1f})",
                flush=True,
            )
        for part in parts:
            after = seconds["after"][part][-1]
            ratios[part].append(seconds["before"][part][-1] / after if after > 0 else math.nan)
        dashboards.append(all(summaries["before"][key] == summaries["after"][key] for key in DASHBOARD))
        valid = torch.isfinite(masks["before"])  # NaN outside the learned pixels
        identical.append(
            torch.equal(valid, torch.isfinite(masks["after"]))
            and torch.equal(masks["before"][valid], masks["after"][valid])
        )
        difference = (masks["after"][valid] / masks["before"][valid] - 1).abs().max()
        largest = max(largest, float(difference))
        print(
            f"round {round_index + 1}: before / after {ratios[parts[0]][-1]:.2f}x, masks identical: {identical[-1]}",
            flush=True,
        )
    print(f"median of {args.rounds} rounds, seconds before -> after [median of per-round ratios before / after]:")
    for part in parts:
        print(
            f"  {part}: {statistics.median(seconds['before'][part]):.1f} -> "
            f"{statistics.median(seconds['after'][part]):.1f} s [{statistics.median(ratios[part]):.2f}x, range "
            f"{min(ratios[part]):.2f}-{max(ratios[part]):.2f}]"
        )
    after = statistics.median(seconds["after"][parts[0]])
    verdict = "within" if after <= TARGET_SECONDS else "OVER"
    print(f"whole fit after: {after:.1f} s, {verdict} the {TARGET_SECONDS:.0f} s target")
    print(
        f"learned masks identical (bit for bit) in {sum(identical)} of {len(identical)} rounds; largest relative "
        f"difference {largest:.1e}; summaries' localization dashboards and mask errors equal in {sum(dashboards)} of "
        f"{len(dashboards)} rounds"
    )


if __name__ == "__main__":
    main()
