"""The fit-mask command: LightningCLI over :class:`MaskFitModule` and :class:`~enmi_torch.data.PairDataModule`.

:func:`fit_mask` runs it with a list of arguments and returns the summary (what ``enmi-fit-mask`` prints);
:mod:`enmi_torch.cli.fit_mask` is the console entry point around it.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import logging
import math
import os
import shutil
import signal
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import torch
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import Callback, TQDMProgressBar
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.utilities.exceptions import SIGTERMException
from torch.utils.data import Subset

from enmi_torch.data import PairDataModule
from enmi_torch.data.pairs import PairDataset
from enmi_torch.training.localization_figure import ANSWER_METHODS, METHOD_MEANINGS, held_out_order
from enmi_torch.training.logger import next_version, run_name
from enmi_torch.training.mask_module import MaskFitModule
from enmi_torch.training.preemption import EXIT_CODES, Preempted, Preemption
from enmi_torch.utils.command import HelpFormatter, dashed_aliases, parser_error, plain_text, with_flag_names
from enmi_torch.utils.files import load_plain_torch
from enmi_torch.utils.resources import config_file

PROG = "enmi-fit-mask"
# A learned mask farther than this from the paper's empirical mask has not converged yet.
CONVERGED = 0.05

DESCRIPTION = f"""\
Learn a per-pixel noise-variance mask from local/prior image pairs, for ENMILoss.

With no arguments it runs the default config (configs/fit_mask.yaml): 2,000 synthetic lidar-like 128x128 pairs,
10 epochs (about half a minute on 2 CPU cores). It writes the mask (variance_mask.pt, .npy, .png) and summary.json
under runs/fit_mask/<data>_N/mask/ of the current folder (<data>: lidar, camera or the pairs folder's name),
TensorBoard dashboards and last.ckpt beside them, and prints how close the mask is to the paper's empirical mask
and to the true variance, and how often each score finds held-out pairs. Use the mask with
ENMILoss(variance_model=LearnedVariance.load(".../variance_mask.pt")).

examples:
  {PROG}                                         # also: python train/fit_mask.py
  {PROG} --data.flavour camera                   # camera-like synthetic pairs
  {PROG} --data.root PAIRS_FOLDER                # your own pairs (enmi-make-pairs writes the format)
  {PROG} --ckpt_path runs/fit_mask/lidar_0/checkpoints/last.ckpt --trainer.max_epochs 20
  {PROG} --trainer.max_epochs 2 --data.train_pairs 64 --data.size 32    # a few-second try (not converged)

Every key of the YAML config is an option, spelt as in the config: --data.KEY, --model.KEY, --trainer.KEY, and
the run's own keys (--ckpt_path, --output_dir, ...), with dots and underscores, as Lightning's commands spell
them (the other enmi commands use dashes: --output-dir). The main ones follow, with the default config's values.
--help_all lists every Lightning Trainer option; --debug shows the full traceback of an error instead of one line."""

# The Trainer options worth listing in the short help, in plain words; --help_all lists them all.
TRAINER_OPTIONS = {
    "--trainer.max_epochs": "epochs to train",
    "--trainer.accelerator": '"cpu", "gpu" (CUDA), "mps" or "auto"',
    "--trainer.devices": "devices to train on (several: add --trainer.strategy ddp)",
    "--trainer.strategy": '"auto", or "ddp" to train on several devices or processes',
}
PLAIN_HELP = {
    **TRAINER_OPTIONS,
    "--config": "a YAML config whose keys are these options (later options override it)",
    "--seed_everything": "seed of the run (true: a random one)",
}
HIDDEN = ("--model", "--data", "--model.shape", "--model.localization_grid", "--print_config")
GROUP_TITLES = {
    "--trainer": "trainer (--help_all lists every option)",
    "--model": "model: the mask and how it is fitted",
    "--data": "data: a folder of pairs (--data.root) or synthetic pairs",
}


class FitMaskParser(LightningArgumentParser):
    """LightningCLI's parser with one-line errors and a short ``--help`` of this command's options."""

    def __init__(self, *args, full_help: bool = False, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.full_help = full_help

    def error(self, message: str, ex: Exception | None = None):
        """One line on stderr, exit code 2 (with "did you mean" for a misspelt option)."""
        parser_error(self, message)

    def format_help(self, *args) -> str:
        """This command's options (run, data, model, a few Trainer ones); every option with ``--help_all``."""
        if self.full_help:
            return super().format_help(*args)
        saved = self._action_groups, self.description, self.usage, self.epilog, self.formatter_class
        defaults = self.get_defaults()  # with the default config's values
        groups = []
        for group in self._action_groups:
            actions = [_short(action, defaults) for action in group._group_actions if _in_short_help(action)]
            if actions and group.title != "Linked arguments":
                short = copy.copy(group)
                short._group_actions, short.description = actions, None
                short.title = GROUP_TITLES.get(actions[0].option_strings[0].split(".")[0], group.title)
                groups.append(short)
        self._action_groups, self.description, self.epilog = groups, DESCRIPTION, None
        self.usage = f"{PROG} [--config FILE] [--data.KEY VALUE] [--model.KEY VALUE] [--trainer.KEY VALUE] ..."
        self.formatter_class = HelpFormatter
        try:
            return super().format_help(*args)
        finally:
            self._action_groups, self.description, self.usage, self.epilog, self.formatter_class = saved


def _in_short_help(action: argparse.Action) -> bool:
    option = action.option_strings[-1] if action.option_strings else ""
    if not option.startswith("--") or option in HIDDEN or option.endswith(".help"):
        return False
    return not option.startswith("--trainer") or action.option_strings[0] in TRAINER_OPTIONS


def _short(action: argparse.Action, defaults) -> argparse.Action:
    """A copy of ``action`` with plain-text help and the default config's value as its default."""
    short = copy.copy(action)
    short.option_strings = [option for option in action.option_strings if not option.endswith("+")]
    short.help = PLAIN_HELP.get(short.option_strings[-1]) or plain_text(action.help or "").rstrip(".")
    short.default = defaults.get(action.dest, action.default)
    if short.metavar is None and short.nargs is None and short.choices is None:
        short.metavar = action.dest.rsplit(".", 1)[-1].upper()
    return short


# The default config's logger save_dir, replaced by --trainer.default_root_dir when that is given.
DEFAULT_SAVE_DIR = "runs"
# The run folder chosen by the main process, for the processes DDP starts (they run the command again).
RUN_FOLDER = "ENMI_FIT_MASK_RUN_FOLDER"
OUTPUT_FILES = ("variance_mask.pt", "variance_mask.npy", "variance_mask.png", "summary.json")


class FitMaskCLI(LightningCLI):
    """LightningCLI with the image shape linked from the data and the run options of this command."""

    def add_arguments_to_parser(self, parser) -> None:
        """Link ``model.shape`` to ``data.shape``; add ``--ckpt_path``, ``--output_dir``, ``--overwrite``, threads."""
        parser.link_arguments("data.shape", "model.shape", compute_fn=list, apply_on="instantiate")
        parser.add_argument("--ckpt_path", type=str | None, default=None, help="resume from this checkpoint file")
        parser.add_argument(
            "--output_dir", type=str | None, default=None, help="folder for the mask files (null: <log dir>/mask)"
        )
        parser.add_argument(
            "--overwrite", type=bool, default=False, help="replace the mask files of an earlier run in --output_dir"
        )
        parser.add_argument(
            "--torch_threads", type=int | None, default=None, help="torch.set_num_threads per process (null: torch's)"
        )
        parser.add_argument("--help_all", action="help", help="list every option, the Trainer's included")

    def __init__(self, *args, created: list[Path] | None = None, **kwargs) -> None:
        # The run folder this command takes is appended to ``created`` (the caller removes it if the run fails early).
        self.created = [] if created is None else created
        super().__init__(*args, **kwargs)

    def before_instantiate_classes(self) -> None:
        """Name the run by its data (``lidar_0``) and take its folder; show the mask's error in the progress bar.

        The logs go under ``--trainer.default_root_dir`` when it is given (Lightning's convention), else under the
        logger's ``save_dir`` (``runs`` in the default config). The run folder is created here, atomically, so runs
        started at once take different folders; the processes that DDP starts use their parent's.
        """
        if self.config["trainer"].get("enable_progress_bar") is not False:
            self.trainer_defaults["callbacks"] = [MaskProgressBar()]
        logger = self.config["trainer"].get("logger")
        init_args = getattr(logger, "init_args", None)
        if init_args is None:
            return
        root_dir = self.config["trainer"].get("default_root_dir")
        if root_dir is not None and init_args.get("save_dir") == DEFAULT_SAVE_DIR:
            init_args.save_dir = str(root_dir)
        if "version" in init_args and init_args.get("version") is None:
            if RUN_FOLDER in os.environ and int(os.environ.get("LOCAL_RANK", "0")) > 0:
                init_args.version = os.environ[RUN_FOLDER]
                return
            data = self.config["data"]
            folder = Path(init_args.get("save_dir") or ".") / (init_args.get("name") or "")
            missing = [path for path in (folder, *folder.parents) if not path.exists()]  # deepest first
            init_args.version = next_version(folder, run_name(data["root"], data["flavour"]))
            self.created += [folder / init_args.version, *missing]


class MaskProgressBar(TQDMProgressBar):
    """The progress bar shows the mask's relative RMS error against the paper's empirical mask, not the run number."""

    def get_metrics(self, trainer, pl_module) -> dict:
        """``mask_error`` in percent (from the second epoch on) and ``val/nll``."""
        items = super().get_metrics(trainer, pl_module)
        items.pop("v_num", None)
        error = items.pop("mask/rel_rms_vs_empirical", None)
        if error is not None:
            items = {"mask_error": f"{100 * float(error):.1f}%", **items}
        return items


class _NoTips(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "Tip:" not in record.getMessage()


class _Held(logging.Filter):
    """Holds the records its handlers would print, to print them once the options are found good."""

    def __init__(self) -> None:
        super().__init__()
        self.records: list[tuple[logging.Handler, logging.LogRecord]] = []
        self.handler: logging.Handler | None = None

    def filter(self, record: logging.LogRecord) -> bool:
        self.records.append((self.handler, record))
        return False


@contextlib.contextmanager
def lightning_chatter_held():
    """Lightning's set-up lines ("Seed set to 0", "GPU available: ...") printed once the set-up succeeds.

    An error about the options then ends the command alone, not after those lines.
    """
    holds = []
    for name in ("lightning.pytorch", "lightning.fabric"):
        for handler in logging.getLogger(name).handlers:
            hold = _Held()
            hold.handler = handler
            handler.addFilter(hold)
            holds.append(hold)
    failed = False
    try:
        yield
    except BaseException:
        failed = True
        raise
    finally:
        for hold in holds:
            hold.handler.removeFilter(hold)
            if not failed:
                for handler, record in hold.records:
                    handler.handle(record)


def quiet_lightning() -> None:
    """Drop Lightning's advertising tips and warnings meant for Lightning's developers, not for this command's users."""
    logging.getLogger("lightning.pytorch.utilities.rank_zero").addFilter(_NoTips())
    warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)", category=FutureWarning)
    # The command hands LightningCLI its own command line as args (so that tests and scripts can call it too).
    warnings.filterwarnings("ignore", message="LightningCLI's args parameter is intended")


def check_checkpoint(path: str, model: torch.nn.Module | None = None) -> None:
    """Refuse a checkpoint that does not load as plain tensors and primitives (``weights_only=True``).

    With ``model``, refuse one whose tensors do not have the model's shapes either (a 16x16 run's checkpoint resumed on
    32x32 data), naming the sizes, instead of ``load_state_dict``'s traceback.
    """
    if not Path(path).is_file():
        raise FileNotFoundError(f"ckpt_path must be a checkpoint file, got {path!r}")
    try:
        checkpoint = load_plain_torch(path, "a plain checkpoint")
    except ValueError as error:
        raise ValueError(f"--ckpt_path {error}") from None
    except Exception as error:  # torch's unpickler fails on foreign files in its own ways (IndexError on some text)
        raise ValueError(
            f"--ckpt_path {path} is refused: it is not a plain checkpoint that loads with weights_only=True "
            f"({type(error).__name__}: {error})"
        ) from None
    if model is None:
        return
    saved = checkpoint.get("state_dict") if isinstance(checkpoint, dict) else None
    if not isinstance(saved, dict):
        raise ValueError(f"--ckpt_path {path!r} is not a Lightning checkpoint: it has no state_dict")
    wanted = model.state_dict()
    differ = [
        f"{key} {tuple(value.shape)} (this run: {tuple(wanted[key].shape)})"
        for key, value in saved.items()
        if key in wanted and isinstance(value, torch.Tensor) and value.shape != wanted[key].shape
    ]
    if differ:
        shape = getattr(model, "shape", None)
        this_run = f" of {shape[0]}x{shape[1]} images" if shape is not None and len(shape) == 2 else ""
        raise ValueError(
            f"--ckpt_path {path!r} was saved by a run of other sizes than this one{this_run}: {', '.join(differ)}; "
            "resume it on the data it was trained on (--data.size, --data.root), or start afresh without --ckpt_path"
        )


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


def check_output_dir(output_dir: Path, overwrite: bool) -> None:
    """Refuse an ``output_dir`` that cannot become a folder, or holds an earlier run's files unless ``overwrite``."""
    existing = next(path for path in (output_dir, *output_dir.absolute().parents) if path.exists())
    if not existing.is_dir():
        which = "which is" if existing == output_dir else f"but {str(existing)!r} on its path is"
        raise ValueError(f"--output_dir must be a folder, got {str(output_dir)!r}, {which} a file")
    if not os.access(existing, os.W_OK):
        raise ValueError(f"--output_dir {str(output_dir)!r} cannot be written: {str(existing)!r} is read-only")
    earlier = [name for name in OUTPUT_FILES if (output_dir / name).exists()]
    if earlier and not overwrite:
        raise FileExistsError(
            f"--output_dir {str(output_dir)!r} already holds {', '.join(earlier)} from an earlier run; choose another "
            "--output_dir, or pass --overwrite true to replace them"
        )


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


# Reading the pairs to check them stops after this many seconds (the fit's first pass reads them all anyway).
CHECK_SECONDS = 3.0
# Ranges suggested for pairs that do not fit --model.value_range: the usual ones, the smallest that covers them.
USUAL_RANGES = (1.0, 256.0, 4096.0, 65536.0)


def check_pairs(datamodule: PairDataModule, bins: int, value_range: Sequence[float]) -> None:
    """Read the pairs (for :data:`CHECK_SECONDS` at most) and refuse them before training if they cannot be fitted.

    Reading raises on a file that cannot be read, of another shape, or with NaN at a valid pixel (naming it); here,
    pairs that ``--model.value_range`` does not resolve (images in [0, 1] against the default [0, 256], 16-bit images)
    are refused with the range to pass, spelt as on the command line.
    """
    from enmi_torch.utils.checks import check_resolved_by_bins

    start = time.perf_counter()
    low, high = float("inf"), float("-inf")  # of the prior images (the maps, noise-free) where there are any
    refused = None
    for dataset in (datamodule.train_set, datamodule.val_set):
        for index in range(len(dataset)):
            item = dataset[index]
            for role in ("local", "prior"):
                values, valid = item[role].reshape(1, -1).double(), item["valid"].reshape(1, -1)
                if role == "prior" and bool(valid.any()):  # noise may spill past the range: the map's range rules
                    low, high = min(low, float(values[valid].min())), max(high, float(values[valid].max()))
                try:
                    check_resolved_by_bins(role, values, valid, bins, tuple(value_range))
                except ValueError:
                    refused = refused or (role, _pair_name(dataset, index))
            if time.perf_counter() - start > CHECK_SECONDS and refused is None:
                return
    if refused is None:
        return
    suggested_low = 0.0 if low >= 0 else math.floor(low)
    suggested_high = next((usual for usual in USUAL_RANGES if high <= usual), math.ceil(high) + 1.0)
    role, name = refused
    raise ValueError(
        f"--model.value_range {[float(value) for value in value_range]} does not fit the pairs: their prior images "
        f"run from {low:.4g} to {high:.4g} (the {role} image of {name} falls in one or two of its {bins} bins); pass "
        f'--model.value_range "[{suggested_low:g}, {suggested_high:g}]"'
    )


def _pair_name(dataset, index: int) -> str:
    """The pair's local file where it has one, else ``pair <index>``."""
    if isinstance(dataset, Subset) and isinstance(dataset.dataset, PairDataset):
        name = dataset.dataset.names[dataset.indices[index]]
        return str(dataset.dataset._files["local"][name])
    return f"pair {index}"


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


# The run's own keys, also accepted with dashes as the other commands spell their options.
RUN_KEYS = ("ckpt_path", "output_dir", "overwrite", "torch_threads", "help_all")


def fit_mask(argv: Sequence[str]) -> dict | None:
    """Run the command with these arguments; returns the summary on the main process (``None`` on the others).

    Everything that can be checked before training is (the options, the checkpoint, the output folder, the pairs),
    before any of Lightning's lines; a run that fails before its first checkpoint leaves no run folder behind.
    """
    created: list[Path] = []
    try:
        return _fit_mask(argv, created)
    except BaseException:
        run_folder, *parents = created or [None]
        if run_folder is not None and not any((run_folder / kept).exists() for kept in ("checkpoints", "mask")):
            shutil.rmtree(run_folder, ignore_errors=True)  # nothing learned there: no folder to clutter TensorBoard
            for parent in parents:  # the folders made for it (runs/fit_mask), if nothing else went there since
                with contextlib.suppress(OSError):
                    parent.rmdir()
        raise


def _fit_mask(argv: Sequence[str], created: list[Path]) -> dict | None:
    default_config = config_file("fit_mask.yaml")
    quiet_lightning()
    arguments = dashed_aliases(argv, RUN_KEYS)
    writer = None
    try:
        with lightning_chatter_held():
            cli = FitMaskCLI(
                MaskFitModule,
                PairDataModule,
                run=False,
                args=arguments,
                parser_class=FitMaskParser,
                parser_kwargs={
                    "prog": PROG,
                    "default_config_files": [str(default_config)],
                    "full_help": "--help_all" in arguments,
                },
                save_config_kwargs={"overwrite": True},
                auto_configure_optimizers=False,
                created=created,
            )
            if cli.config["torch_threads"] is not None:
                if cli.config["torch_threads"] < 1:
                    raise ValueError(f"--torch_threads must be an int >= 1 or null, got {cli.config['torch_threads']}")
                torch.set_num_threads(cli.config["torch_threads"])
            ckpt_path = cli.config["ckpt_path"]
            if ckpt_path is not None:
                check_checkpoint(ckpt_path, cli.model)
            output_dir = None if cli.config["output_dir"] is None else Path(cli.config["output_dir"])
            if output_dir is not None:
                check_output_dir(output_dir, cli.config["overwrite"])
            world = cli.trainer.num_devices * cli.trainer.num_nodes
            if cli.datamodule.batch_size % world:
                raise ValueError(
                    f"--data.batch_size must be divisible by the number of processes {world}, "
                    f"got {cli.datamodule.batch_size}"
                )
            if cli.trainer.is_global_zero and cli.config["data"]["root"] is not None:  # synthetic pairs fit by design
                check_pairs(cli.datamodule, cli.model.hparams.bins, cli.model.hparams.value_range)
            for callback in cli.trainer.callbacks:
                if isinstance(callback, Preemption):
                    callback.command = [PROG, *argv]
            writer = MaskWriter(output_dir)
            cli.trainer.callbacks.append(writer)
        start = time.perf_counter()
        if created:
            os.environ[RUN_FOLDER] = created[0].name
        try:
            cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=ckpt_path, weights_only=True)
        except SIGTERMException as stop:  # Lightning ends a SIGTERM with exit code 0: a preemption is not a success
            if isinstance(stop, Preempted):
                raise
            raise Preempted(EXIT_CODES[signal.SIGTERM]) from stop
        finally:
            os.environ.pop(RUN_FOLDER, None)
    except MisconfigurationException as error:  # Lightning's word for a bad option (devices, strategy, ...)
        raise ValueError(str(error)) from error
    except (ValueError, TypeError, FileNotFoundError) as error:
        message = with_flag_names(str(error), cli_config_keys())
        if writer is not None and writer.written is not None:
            message += f" (the mask trained before the error is in {writer.written.parent})"
        if message == str(error):
            raise
        raise type(error)(message) from error
    seconds = time.perf_counter() - start
    log_dir = cli.trainer.log_dir  # a collective under DDP: every process asks
    output_dir = writer.folder(cli.trainer)
    if not cli.trainer.is_global_zero:
        return None
    data = cli.config["data"]
    source = data["root"] or f"synthetic, {data['flavour']}-like"
    # Checked before training; the files there now are this run's own (written before each evaluation).
    summary = write_outputs(cli.model, cli.trainer, output_dir, log_dir, seconds, source, overwrite=True)
    print_summary(summary)
    return summary


def cli_config_keys() -> dict[str, str]:
    """The flag of each ``--data.*`` and ``--model.*`` key by its name (``train_pairs``: ``--data.train_pairs``)."""
    import inspect

    flags = {}
    for group, target in (("model", MaskFitModule), ("data", PairDataModule)):
        for name in inspect.signature(target.__init__).parameters:
            if name != "self":
                flags.setdefault(name, f"--{group}.{name}")
    return flags


# The simple types the quick reference checks a value against (the other options are the full parser's alone).
SIMPLE_TYPES = {int: "int", float: "float", bool: "bool", int | None: "int|null", bool | None: "bool|null"}


def quick_reference(columns: int) -> dict:
    """What ``enmi-fit-mask`` answers without Lightning (:mod:`enmi_torch.cli.fit_mask_quick`).

    The help, formatted at ``columns``, and every option with its simple type (``"int"``, ``"bool|null"``, ...;
    ``None`` for the others).
    """
    import importlib.metadata
    from unittest import mock

    class Caught(Exception):
        pass

    parsers = []

    class Parser(FitMaskParser):
        def parse_args(self, *args, **kwargs):
            parsers.append(self)
            raise Caught

    with contextlib.suppress(Caught), mock.patch.dict(os.environ, {"COLUMNS": str(columns)}):
        FitMaskCLI(
            MaskFitModule,
            PairDataModule,
            run=False,
            args=[],
            parser_class=Parser,
            parser_kwargs={"prog": PROG, "default_config_files": [str(config_file("fit_mask.yaml"))]},
            auto_configure_optimizers=False,
        )
    (parser,) = parsers
    with mock.patch.dict(os.environ, {"COLUMNS": str(columns)}):
        text = parser.format_help()
    options = {}
    for action in parser._actions:
        hint = getattr(action, "_typehint", None)
        for option in action.option_strings:
            if option.startswith("--") and not option.endswith("+"):
                options[option] = SIMPLE_TYPES.get(hint) if action.nargs is None else None
    versions = {name: importlib.metadata.version(name) for name in ("lightning", "jsonargparse")}
    return {"help": text, "options": options, "run_keys": list(RUN_KEYS), "versions": versions}
