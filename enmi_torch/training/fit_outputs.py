"""What the fit-mask command writes: the mask during the fit, then the mask files, ``summary.json`` and its printout."""

from __future__ import annotations

import json
import math
from pathlib import Path

from lightning.pytorch.callbacks import Callback

from enmi_torch.training.fit_checks import check_output_dir
from enmi_torch.training.localization_figure import ANSWER_METHODS, METHOD_MEANINGS, held_out_order
from enmi_torch.training.mask_module import MaskFitModule

# A learned mask farther than this from the paper's empirical mask has not converged yet.
CONVERGED = 0.05


class MaskWriter(Callback):
    """Writes the mask (``.pt``, ``.npy``) before each held-out evaluation, so that no error there loses the fit.

    ``output_dir``: the folder; ``None`` takes ``<log dir>/mask``. :attr:`written` is the ``.pt`` file once written.
    """

    def __init__(self, output_dir: Path | None) -> None:
        self.output_dir = output_dir
        self.written: Path | None = None

    def folder(self, trainer) -> Path:
        """The mask's folder."""
        return self.output_dir or Path(trainer.log_dir) / "mask"

    def on_validation_start(self, trainer, pl_module: MaskFitModule) -> None:
        """Save the mask trained so far (the main process; every process holds the same mask)."""
        if trainer.sanity_checking or pl_module.mask is None:
            return
        folder = self.folder(trainer)  # every process asks: trainer.log_dir is a collective under DDP
        if not trainer.is_global_zero:
            return
        folder.mkdir(parents=True, exist_ok=True)
        for suffix in ("pt", "npy"):
            pl_module.mask.save(folder / f"variance_mask.{suffix}")
        self.written = folder / "variance_mask.pt"


def finite_for_json(value: object, where: str = "") -> tuple[object, list[str]]:
    """``value`` with every NaN or inf float replaced by ``None`` (JSON has neither), and the keys where it was."""
    if isinstance(value, float) and not math.isfinite(value):
        return None, [where or "value"]
    if isinstance(value, dict):
        pairs = [(key, finite_for_json(item, f"{where}.{key}" if where else str(key))) for key, item in value.items()]
        return {key: item for key, (item, _) in pairs}, [path for _, (_, paths) in pairs for path in paths]
    if isinstance(value, (list, tuple)):
        items = [finite_for_json(item, f"{where}[{index}]") for index, item in enumerate(value)]
        return [item for item, _ in items], [path for _, paths in items for path in paths]
    return value, []


def write_outputs(
    model: MaskFitModule,
    trainer,
    output_dir: Path,
    log_dir: str,
    seconds: float,
    source: str,
    *,
    overwrite: bool = False,
) -> dict:
    """Write the mask files and ``summary.json``; returns the summary (``source``: where the pairs came from).

    Refuses to replace an earlier run's files unless ``overwrite``.
    """
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
        "source": source,
        "shape": list(model.shape),
        "train_pairs": datamodule.num_train_pairs,
        "val_pairs": len(datamodule.val_set),
        "epochs": trainer.current_epoch,
        "seconds": seconds,
        "train_epoch_seconds": model.epoch_seconds,
        "learned_pixels": int(model.mask.valid.sum()),
        "errors": model.mask_errors(),
        "localization_pairs": min(model.hparams.localization_pairs, len(datamodule.val_set)),
        "localization": _by_set(metrics, "localization/"),
        "localization_z": _by_set(metrics, "localization_z/"),
    }
    written, non_finite = finite_for_json(summary)
    (output_dir / "summary.json").write_text(json.dumps(written, indent=2, allow_nan=False) + "\n")
    if non_finite:
        print(f"summary.json: {', '.join(non_finite)} not finite, written as null")
    return summary


def _by_set(metrics: dict, prefix: str) -> dict[str, dict[str, float]]:
    """``{"<prefix><set>/<method>": value}`` as ``{set: {method: value}}``."""
    nested: dict[str, dict[str, float]] = {}
    for key, value in metrics.items():
        if key.startswith(prefix) and key.count("/") == 2:
            held_out, method = key[len(prefix) :].split("/")
            nested.setdefault(held_out, {})[method] = float(value)
    return nested


def _localization_lines(rates: dict[str, dict[str, float]], pairs: int) -> list[str]:
    """A table: the share of held-out pairs each method located (rows), at each noise level (columns).

    Rows are named as in TensorBoard (``localization/<set>/<method>``); the answer's lines first, what they mean below.
    """
    sets = held_out_order(rates)
    methods = [method for method in METHOD_MEANINGS if any(method in rates[name] for name in sets)]
    stderr = 0.5 / pairs**0.5
    header = "".join(f"{name:>11}" for name in sets)
    lines = [
        f"  held-out pairs located within one pixel, share of {pairs} (standard error at most {stderr:.2f}):",
        f"    {'':<19}{header}",
    ]
    for method in methods:
        cells = "".join(f"{rates[name][method]:>11.3f}" if method in rates[name] else f"{'-':>11}" for name in sets)
        lines.append(f"    {method:<19}{cells}")
    shown = [method for method in ANSWER_METHODS if method in methods]
    lines += [f"    {method}: {METHOD_MEANINGS[method]}" for method in shown]
    return lines


def print_summary(summary: dict) -> None:
    """Print how good the mask is, where the outputs are, and how to use the mask."""
    errors = summary["errors"]
    height, width = summary["shape"]
    lines = [
        f"Variance mask learned from {summary['train_pairs']} pairs of {height}x{width} ({summary['source']}), "
        f"{summary['epochs']} epochs, {summary['seconds']:.1f} s ({summary['learned_pixels']} pixels learned)",
        f"  relative RMS error vs the paper's empirical mask: {100 * errors['rel_rms_vs_empirical']:.2f} %",
    ]
    if "rel_rms_vs_truth" in errors:
        lines.append(
            f"  relative RMS error vs the true variance:          {100 * errors['rel_rms_vs_truth']:.2f} % "
            f"(empirical mask: {100 * errors['empirical_rel_rms_vs_truth']:.2f} %)"
        )
    if errors["rel_rms_vs_empirical"] > CONVERGED:
        lines.append(
            f"  not converged after {summary['epochs']} epochs: train longer (--trainer.max_epochs) before using it"
        )
    if summary["localization"]:
        lines += _localization_lines(summary["localization"], summary["localization_pairs"])
    mask = summary["files"]["pt"]
    lines += [
        f"  mask files:  {mask} (.npy, .png and summary.json beside it)",
        f"  checkpoint:  {summary['last_checkpoint']}",
        f"  dashboards:  tensorboard --logdir {Path(summary['log_dir']).parent}",
        "Use it in ENMI:",
        f'  ENMILoss(variance_model=LearnedVariance.load("{mask}"))',
    ]
    print("\n".join(lines))
