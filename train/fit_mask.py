"""Learn a per-pixel noise variance mask from local/prior image pairs, for ``ENMILoss``.

Run from the repository root::

    python train/fit_mask.py                                   # configs/fit_mask.yaml: 2,000 synthetic lidar-like pairs
    python train/fit_mask.py --data.flavour camera             # camera-like synthetic pairs
    python train/fit_mask.py --data.root PAIRS_FOLDER          # your own pairs (format: enmi_torch.data.pairs)
    python train/fit_mask.py --config configs/fit_mask_smoke.yaml
    python train/fit_mask.py --ckpt_path train/runs/fit_mask/version_0/checkpoints/last.ckpt --trainer.max_epochs 20
    python train/fit_mask.py --help

It writes the mask (``variance_mask.pt``, ``.npy``, ``.png``) and ``summary.json`` under ``<log dir>/mask`` (or
``--output_dir``), TensorBoard dashboards and checkpoints under the log dir, and prints a summary. It refuses, before
training, an ``--output_dir`` that holds an earlier run's mask files, unless given ``--overwrite true``.
"""

from __future__ import annotations

import json
import pickle
import sys
import time
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import torch  # noqa: E402
from lightning.pytorch.cli import LightningCLI  # noqa: E402

from enmi_torch.data import PairDataModule  # noqa: E402
from train.mask_module import MaskFitModule  # noqa: E402

DEFAULT_CONFIG = ROOT / "configs" / "fit_mask.yaml"
OUTPUT_FILES = ("variance_mask.pt", "variance_mask.npy", "variance_mask.png", "summary.json")


class FitMaskCLI(LightningCLI):
    """LightningCLI with the image shape linked from the data and the run options of this command."""

    def add_arguments_to_parser(self, parser) -> None:
        """Link ``model.shape`` to ``data.shape``; add ``--ckpt_path``, ``--output_dir``, ``--overwrite``, threads."""
        parser.link_arguments("data.shape", "model.shape", apply_on="instantiate")
        parser.add_argument("--ckpt_path", type=str | None, default=None, help="resume from this checkpoint file")
        parser.add_argument(
            "--output_dir", type=str | None, default=None, help="folder for the mask files (default: <log dir>/mask)"
        )
        parser.add_argument(
            "--overwrite", type=bool, default=False, help="replace the mask files of an earlier run in --output_dir"
        )
        parser.add_argument(
            "--torch_threads", type=int | None, default=None, help="torch.set_num_threads per process (null: torch's)"
        )


def check_checkpoint(path: str) -> None:
    """Refuse a checkpoint that does not load as plain tensors and primitives (``weights_only=True``)."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"ckpt_path must be a checkpoint file, got {path!r}")
    try:
        torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError, zipfile.BadZipFile, OSError) as error:
        raise ValueError(
            f"{path} is refused: it is not a plain checkpoint that loads with weights_only=True ({error})"
        ) from None


def check_output_dir(output_dir: Path, overwrite: bool) -> None:
    """Refuse an ``output_dir`` holding an earlier run's files unless ``overwrite``."""
    earlier = [name for name in OUTPUT_FILES if (output_dir / name).exists()]
    if earlier and not overwrite:
        raise FileExistsError(
            f"--output_dir {str(output_dir)!r} already holds {', '.join(earlier)} from an earlier run; choose another "
            "--output_dir, or pass --overwrite true to replace them"
        )


def write_outputs(
    model: MaskFitModule, trainer, output_dir: Path, log_dir: str, seconds: float, *, overwrite: bool = False
) -> dict:
    """Write the mask files and ``summary.json``, refusing to replace an earlier run's unless ``overwrite``."""
    import matplotlib.pyplot as plt

    check_output_dir(output_dir, overwrite)
    output_dir.mkdir(parents=True, exist_ok=True)
    paths = {suffix: output_dir / f"variance_mask.{suffix}" for suffix in ("pt", "npy", "png")}
    model.mask.save(paths["pt"])
    model.mask.save(paths["npy"])
    figure = model.figure()
    figure.savefig(paths["png"], dpi=90)
    plt.close(figure)
    datamodule = trainer.datamodule
    metrics = trainer.callback_metrics
    summary = {
        "files": {suffix: str(path) for suffix, path in paths.items()},
        "log_dir": log_dir,
        "last_checkpoint": getattr(trainer.checkpoint_callback, "last_model_path", "") or None,
        "train_pairs": datamodule.num_train_pairs,
        "val_pairs": len(datamodule.val_set),
        "epochs": trainer.current_epoch,
        "seconds": seconds,
        "train_epoch_seconds": model.epoch_seconds,
        "learned_pixels": int(model.mask.valid.sum()),
        "errors": model.mask_errors(),
        "localization_pairs": min(model.hparams.localization_pairs, len(datamodule.val_set)),
        "localization": {
            key.split("/", 1)[1]: float(value) for key, value in metrics.items() if key.startswith("localization/")
        },
        "localization_z": {
            key.split("/", 1)[1]: float(value) for key, value in metrics.items() if key.startswith("localization_z/")
        },
    }
    (output_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def print_summary(summary: dict) -> None:
    """Print where the outputs are and how good the mask is."""
    errors = summary["errors"]
    lines = [
        f"Variance mask learned from {summary['train_pairs']} pairs, {summary['epochs']} epochs, "
        f"{summary['seconds']:.1f} s ({summary['learned_pixels']} learned pixels)",
        f"  mask files:   {summary['files']['pt']}  (.npy, .png beside it)",
        f"  checkpoint:   {summary['last_checkpoint']}",
        f"  dashboards:   tensorboard --logdir {Path(summary['log_dir']).parent}",
        f"  relative RMS error vs the paper's empirical mask: {100 * errors['rel_rms_vs_empirical']:.2f} %",
    ]
    if "rel_rms_vs_truth" in errors:
        lines.append(
            f"  relative RMS error vs the true variance:          {100 * errors['rel_rms_vs_truth']:.2f} % "
            f"(empirical mask: {100 * errors['empirical_rel_rms_vs_truth']:.2f} %)"
        )
    if summary["localization"]:
        scores = ", ".join(f"{name} {value:.3f}" for name, value in sorted(summary["localization"].items()))
        lines.append(f"  localization success on {summary['localization_pairs']} held-out pairs: {scores}")
    print("\n".join(lines))


def main(args: list[str] | None = None) -> dict | None:
    """Run the command; returns the summary on the main process (``None`` on the others)."""
    cli = FitMaskCLI(
        MaskFitModule,
        PairDataModule,
        run=False,
        args=args,
        parser_kwargs={"default_config_files": [str(DEFAULT_CONFIG)]},
        save_config_kwargs={"overwrite": True},
    )
    if cli.config["torch_threads"] is not None:
        torch.set_num_threads(cli.config["torch_threads"])
    ckpt_path = cli.config["ckpt_path"]
    if ckpt_path is not None:
        check_checkpoint(ckpt_path)
    if cli.config["output_dir"] is not None:
        check_output_dir(Path(cli.config["output_dir"]), cli.config["overwrite"])
    start = time.perf_counter()
    cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=ckpt_path, weights_only=True)
    seconds = time.perf_counter() - start
    log_dir = cli.trainer.log_dir  # a collective under DDP: every process asks
    if not cli.trainer.is_global_zero:
        return None
    output_dir = Path(cli.config["output_dir"] or Path(log_dir) / "mask")
    summary = write_outputs(cli.model, cli.trainer, output_dir, log_dir, seconds, overwrite=cli.config["overwrite"])
    print_summary(summary)
    return summary


if __name__ == "__main__":
    main()
