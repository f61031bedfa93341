"""The fit-mask command: LightningCLI over :class:`MaskFitModule` and :class:`~enmi_torch.data.PairDataModule`.

:func:`fit_mask` runs it with a list of arguments and returns the summary (what ``enmi-fit-mask`` prints);
:mod:`enmi_torch.cli.fit_mask` is the console entry point around it. What it checks before training is in
:mod:`~enmi_torch.training.fit_checks`, what it writes in :mod:`~enmi_torch.training.fit_outputs`.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import logging
import os
import shutil
import signal
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import torch
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.utilities.exceptions import SIGTERMException

from enmi_torch.data import PairDataModule
from enmi_torch.training.fit_checks import (
    OutputClaim,
    check_checkpoint,
    check_learnable,
    check_pairs,
    claim_output_dir,
)
from enmi_torch.training.fit_outputs import MaskWriter, print_summary, write_outputs
from enmi_torch.training.logger import next_version, run_name
from enmi_torch.training.mask_module import MaskFitModule
from enmi_torch.training.preemption import EXIT_CODES, Preempted, Preemption
from enmi_torch.utils.command import (
    HelpFormatter,
    check_text_files,
    dashed_aliases,
    parser_error,
    plain_text,
    with_flag_names,
)
from enmi_torch.utils.files import check_folder_to_write
from enmi_torch.utils.options import OptionError
from enmi_torch.utils.resources import config_file

PROG = "enmi-fit-mask"

DESCRIPTION = f"""\
Learn a per-pixel noise-variance mask from local/prior image pairs, for localize, ECRLoss and ENMILoss.

With no arguments it runs the default config (configs/fit_mask.yaml): 2,000 synthetic lidar-like 128x128 pairs,
10 epochs (a few minutes on 2 CPU cores, most of them the held-out comparison). It writes the mask
(variance_mask.pt, .npy, .png) and summary.json under runs/fit_mask/<data>_N/mask/ of the current folder (<data>:
lidar, camera or the pairs folder's name), TensorBoard dashboards and last.ckpt beside them, and prints how close the
mask is to the paper's empirical mask and to the true variance, and how often localize finds held-out pairs with
the library's default score ECR() and with ENMI (the paper's), with the mask and with uniform variances, at two
noise levels read from the held-out pairs (--model.localization_noise "[1, 16]": factors by hand). Use the mask with
localize(captured, prior_map, LearnedVariance.load(".../variance_mask.pt")), ECRLoss or ENMILoss(variance_model=...).

examples:
  {PROG}                                         # also: python -m enmi_torch.cli.fit_mask
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
            check_folder_to_write(root_dir, "--trainer.default_root_dir")
        check_folder_to_write(init_args.get("save_dir") or ".", "--trainer.logger.init_args.save_dir")
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


# The run's own keys, also accepted with dashes as the other commands spell their options.
RUN_KEYS = ("ckpt_path", "output_dir", "overwrite", "torch_threads", "help_all")


def fit_mask(argv: Sequence[str]) -> dict | None:
    """Run the command with these arguments; returns the summary on the main process (``None`` on the others).

    Everything that can be checked before training is (the options, the checkpoint, the output folder, the pairs),
    before any of Lightning's lines; a run that fails before its first checkpoint leaves no run folder behind. The
    mask's folder is held by this run until it ends (:func:`~enmi_torch.training.fit_checks.claim_output_dir`): a run
    started meanwhile with the same ``--output_dir`` is refused before it trains, and an earlier run's mask is never
    replaced without ``--overwrite true``.
    """
    created: list[Path] = []
    claims: list[OutputClaim] = []  # the mask's folder, held until the run ends
    try:
        return _fit_mask(argv, created, claims)
    except BaseException:
        for claim in claims:
            claim.release()  # first: a mask folder made for the claim and left empty goes
        run_folder, *parents = created or [None]
        if run_folder is not None and not any((run_folder / kept).exists() for kept in ("checkpoints", "mask")):
            shutil.rmtree(run_folder, ignore_errors=True)  # nothing learned there: no folder to clutter TensorBoard
            for parent in parents:  # the folders made for it (runs/fit_mask), if nothing else went there since
                with contextlib.suppress(OSError):
                    parent.rmdir()
        raise
    finally:
        for claim in claims:
            claim.release()


def _fit_mask(argv: Sequence[str], created: list[Path], claims: list[OutputClaim]) -> dict | None:
    default_config = config_file("fit_mask.yaml")
    quiet_lightning()
    arguments = dashed_aliases(argv, RUN_KEYS)
    check_text_files(arguments, "--config")
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
                check_folder_to_write(output_dir, "--output_dir")
            cli.model.build_mask(cli.datamodule.truth)  # the mask's options and analytic map, before any work
            world = cli.trainer.num_devices * cli.trainer.num_nodes
            if cli.datamodule.batch_size % world:
                raise ValueError(
                    f"--data.batch_size must be divisible by the number of processes {world}, "
                    f"got {cli.datamodule.batch_size}"
                )
            if cli.trainer.is_global_zero:
                check_learnable(cli.datamodule, cli.config["data"])
                if cli.config["data"]["root"] is not None:  # synthetic pairs fit by design
                    check_pairs(cli.datamodule, cli.model.hparams.bins, cli.model.hparams.value_range)
            for callback in cli.trainer.callbacks:
                if isinstance(callback, Preemption):
                    callback.command = [PROG, *argv]
            writer = MaskWriter(output_dir)
            cli.trainer.callbacks.append(writer)
            if cli.trainer.is_global_zero:  # the mask's folder, taken atomically: runs started at once never share one
                folder = "--output_dir" if output_dir is not None else "the run's mask folder"
                claims.append(claim_output_dir(writer.folder(cli.trainer), cli.config["overwrite"], folder))
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
        flags = cli_config_keys()
        if isinstance(error, OptionError):  # a refusal naming several options: each as its flag
            message = error.spelled(lambda name, value: f"{flags.get(name, name)} {value}")
        else:
            message = with_flag_names(str(error), flags)
        if writer is not None and writer.written is not None:
            message += f" (the mask trained before the error is in {writer.written.parent})"
        if message == str(error):
            raise
        raise (ValueError if isinstance(error, OptionError) else type(error))(message) from error
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
