"""What the fit-mask command writes: the mask during the fit, then the mask files, ``summary.json`` and its printout."""

from __future__ import annotations

import json
import math
from pathlib import Path

from lightning.pytorch.callbacks import Callback

from enmi_torch.training.fit_checks import check_output_dir
from enmi_torch.training.held_out import LEVEL_EASY, LEVEL_HARD, METHOD_MEANINGS, TARGET, held_out_order
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
        "localization_levels": model.levels or {},
        "localization_calibration": _calibration(model),
        "localization_grid": [1.0, *model.hparams.localization_grid],
        "value_range": list(model.hparams.value_range),
        "localization": _by_set(model.held_out.rates if model.held_out is not None else {}),
        "localization_z": _by_set(model.held_out.margins if model.held_out is not None else {}),
        "localization_paired": {
            held_out: {name: {"mean": mean, "se": error} for name, (mean, error) in differences.items()}
            for held_out, differences in (model.held_out.paired if model.held_out is not None else {}).items()
        },
    }
    written, non_finite = finite_for_json(summary)
    (output_dir / "summary.json").write_text(json.dumps(written, indent=2, allow_nan=False) + "\n")
    if non_finite:
        print(f"summary.json: {', '.join(non_finite)} not finite, written as null")
    return summary


def _calibration(model: MaskFitModule) -> dict | None:
    """How the held-out levels were read (``None``: given by hand), with the best method at each factor."""
    calibration = model.calibration
    if calibration is None:
        return None
    return {**calibration._asdict(), "leaders": calibration.leaders()}


def _by_set(values: dict[str, float]) -> dict[str, dict[str, float]]:
    """``{"<set>/<method>": value}`` as ``{set: {method: value}}``, in the table's order.

    Sets easiest first, methods the library's default score first; values that are not finite (a margin that could
    not be measured) are left out.
    """
    nested: dict[str, dict[str, float]] = {}
    for held_out in held_out_order({key.split("/")[0] for key in values}):
        for method in METHOD_MEANINGS:
            value = values.get(f"{held_out}/{method}")
            if value is not None and math.isfinite(value):
                nested.setdefault(held_out, {})[method] = float(value)
    return nested


def _level_lines(summary: dict) -> list[str]:
    """How the held-out levels were chosen: the calibration ladder and the levels it picked, or the factors given."""
    levels = summary["localization_levels"]
    calibration = summary["localization_calibration"]
    if calibration is None:
        factors = ", ".join(f"x{factor:g}" for factor in levels.values())
        return [f"  held-out levels given by hand (--model.localization_noise): {factors}"]
    low, high = summary["value_range"]
    lines = [
        f"  held-out levels read from {calibration['pairs']} held-out pairs: their residual local - prior amplified by "
        f"a factor, clipped to [{low:g}, {high:g}]",
        "    factor     " + "".join(f"{f'x{factor:g}':>7}" for factor in calibration["factors"]),
        "    best share " + "".join(f"{share:>7.2f}" for share in calibration["best"]),
    ]
    hard, easy = f"x{levels[LEVEL_HARD]:g}", f"x{levels[LEVEL_EASY]:g}"
    where = {
        "yes": f"where the best method finds {TARGET:g} of the pairs (L50)",
        "below": f"the lowest factor tried, where the best method still finds less than {TARGET:g} of the pairs",
        "above": f"the highest factor tried, where the best method still finds {TARGET:g} of the pairs or more",
    }[calibration["bracketed"]]
    lines += [f"    {LEVEL_HARD} {hard}: {where}", f"    {LEVEL_EASY} {easy}: a quarter of {LEVEL_HARD}'s factor"]
    return lines


def _legend(grid: list[float]) -> list[str]:
    grid = sorted(grid)
    factors = ", ".join(f"{factor:g}" for factor in grid[:-1]) + f" or {grid[-1]:g}"
    return [
        "    ecr_*: ECR(), the library's default score, searched as localize searches (its finalist stage included)",
        "    enmi_*: ENMI, the paper's score; nmi, ncc: controls without a variance",
        "    *_learned: the learned mask; *_true: the true variance (where the pairs name it); *_uniform: one uniform",
        f"    variance, the mask's mean; *_best_uniform: the best of the mask's mean times {factors} (an oracle)",
    ]


def _localization_lines(summary: dict) -> list[str]:
    """A table: the share of held-out pairs each method located (rows), at each held-out level (columns).

    Rows are named as in TensorBoard (``localization/<set>/<method>``), the library's default score first; what they
    mean below, then the learned mask's paired differences against its controls.
    """
    rates, pairs = summary["localization"], summary["localization_pairs"]
    sets = held_out_order(rates)
    methods = [method for method in METHOD_MEANINGS if any(method in rates[name] for name in sets)]
    stderr = 0.5 / pairs**0.5
    width = max(13, *(len(name) + 2 for name in sets))
    lines = [
        f"  held-out pairs located within one pixel by localize, share of {pairs} (standard error at most "
        f"{stderr:.2f}):",
        f"    {'':<18}" + "".join(f"{name:>{width}}" for name in sets),
    ]
    for method in methods:
        cells = "".join(
            f"{rates[name][method]:>{width}.3f}" if method in rates[name] else f"{'-':>{width}}" for name in sets
        )
        lines.append(f"    {method:<18}{cells}")
    lines += _legend(summary["localization_grid"])
    paired = summary["localization_paired"]
    comparisons = list(dict.fromkeys(name for name in sets for name in paired.get(name, {})))
    if comparisons:
        lines.append(f"  paired differences over the same {pairs} pairs (mean ± standard error):")
        width = max(17, width)
        lines.append(f"    {'':<36}" + "".join(f"{name:>{width}}" for name in sets))
        for comparison in comparisons:
            cells = "".join(
                f"{paired[name][comparison]['mean']:>+{width - 8}.3f} ± {paired[name][comparison]['se']:.3f}"
                if comparison in paired.get(name, {})
                else f"{'-':>{width}}"
                for name in sets
            )
            lines.append(f"    {comparison:<36}{cells}")
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
        lines += _level_lines(summary) + _localization_lines(summary)
    mask = summary["files"]["pt"]
    lines += [
        f"  mask files:  {mask} (.npy, .png and summary.json beside it)",
        f"  checkpoint:  {summary['last_checkpoint']}",
        f"  dashboards:  tensorboard --logdir {Path(summary['log_dir']).parent}",
        "Use the mask, with the library's default score first:",
        f'  mask = LearnedVariance.load("{mask}")',
        "  localize(captured, prior_map, mask)   # ECR(), localize's default score",
        "  ECRLoss(variance_model=mask)          # its loss (registration, training)",
        "  ENMILoss(variance_model=mask)         # ENMI, the paper's score",
    ]
    print("\n".join(lines))
