"""Benchmark of ``enmi-fit-mask``: fitting 2,000 pairs of 128 x 128 (target: at most 2 minutes on 2 cores).

    python data_tools/bench_fit_mask.py

Runs the default configuration (configs/fit_mask.yaml) once in this process, logs to a temporary folder, and prints
the whole fit's wall time, the median training epoch and the pairs per second. The reference, measured in the same
process first, is the median time of generating one epoch of pairs without fitting (3 runs): the ratio of an epoch
to it says how much the fitting costs on top of the data, whatever the machine's speed.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time

import torch

from enmi_torch.data import PairDataModule
from enmi_torch.training.fit_mask import fit_mask

TARGET_SECONDS = 120.0


def data_epoch_seconds(pairs: int, size: int, batch_size: int, repeats: int = 3) -> list[float]:
    """Seconds to draw one epoch of training pairs through the data loader, no fitting."""
    datamodule = PairDataModule(train_pairs=pairs, val_pairs=2, size=size, batch_size=batch_size)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _batch in datamodule.train_dataloader():
            pass
        times.append(time.perf_counter() - start)
    return times


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=int, default=2000)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--torch-threads", type=int, default=1, help="as configs/fit_mask.yaml (default 1)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.torch_threads)
    print(
        f"fit_mask benchmark: {args.pairs} pairs of {args.size}x{args.size}, {args.epochs} epochs, "
        f"batch {args.batch_size}; torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"{os.cpu_count()} CPUs"
    )
    reference = data_epoch_seconds(args.pairs, args.size, args.batch_size)
    reference_median = statistics.median(reference)
    print(
        f"reference, one epoch of pair generation without fitting: median {reference_median:.2f} s over "
        f"{len(reference)} runs ({args.pairs / reference_median:.0f} pairs/s)"
    )
    with tempfile.TemporaryDirectory() as folder:
        summary = fit_mask(
            [
                *("--trainer.logger.init_args.save_dir", folder, "--trainer.enable_progress_bar", "false"),
                *("--data.train_pairs", str(args.pairs), "--data.size", str(args.size)),
                *("--data.batch_size", str(args.batch_size), "--trainer.max_epochs", str(args.epochs)),
                *("--trainer.check_val_every_n_epoch", str(max(1, args.epochs // 2))),
                *("--torch_threads", str(args.torch_threads)),
            ]
        )
    epochs = summary["train_epoch_seconds"]
    epoch_median = statistics.median(epochs)
    verdict = "within" if summary["seconds"] <= TARGET_SECONDS else "OVER"
    print(
        f"whole fit (statistics pass, {len(epochs)} epochs, validations): {summary['seconds']:.1f} s, "
        f"{verdict} the {TARGET_SECONDS:.0f} s target"
    )
    print(
        f"training epoch: median {epoch_median:.2f} s over {len(epochs)} epochs, "
        f"{args.pairs / epoch_median:.0f} pairs/s; ratio to the reference {epoch_median / reference_median:.2f}"
    )


if __name__ == "__main__":
    main()
