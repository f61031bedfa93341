"""What the fit-mask command checks before it trains: the model's options, the pairs, the checkpoint, the output.

Each raises a ``ValueError`` (or ``FileNotFoundError``, ``FileExistsError``) naming the option as the command line
spells it, before any of Lightning's lines; the model's own options (:func:`check_model_options`, from
:class:`~enmi_torch.training.mask_module.MaskFitModule`'s constructor) raise
:class:`~enmi_torch.utils.options.OptionError` where a message names more than one, so that the command spells each
as its flag. The output folder is claimed
(:func:`claim_output_dir`): two runs started at once never write into one.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import Subset

from enmi_torch.data import PairDataModule
from enmi_torch.data.pairs import PairDataset
from enmi_torch.utils.checks import (
    check_bins,
    check_bool,
    check_image_shape,
    check_non_negative_int,
    check_positive_int,
    check_positive_number,
    check_value_range,
)
from enmi_torch.utils.files import check_folder_to_write, load_plain_torch
from enmi_torch.utils.options import OptionError, OptionRule, check_option_rules

# The files a run writes into its output folder.
OUTPUT_FILES = ("variance_mask.pt", "variance_mask.npy", "variance_mask.png", "summary.json")

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


def check_checkpoint(path: str, model: torch.nn.Module | None = None) -> None:
    """Refuse a checkpoint that does not load as plain tensors and primitives (``weights_only=True``).

    With ``model``, refuse one whose tensors do not have the model's shapes either (a 16x16 run's checkpoint resumed on
    32x32 data), naming the sizes, instead of ``load_state_dict``'s traceback.
    """
    if Path(path).is_dir():
        raise ValueError(f"--ckpt_path must be a checkpoint file, got the folder {path!r}")
    if not Path(path).is_file():
        raise FileNotFoundError(f"--ckpt_path must be a checkpoint file, got {path!r} (no such file)")
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


def check_output_dir(output_dir: Path, overwrite: bool) -> None:
    """Refuse an ``output_dir`` that cannot become a folder, or holds an earlier run's files unless ``overwrite``."""
    check_folder_to_write(output_dir, "--output_dir")
    earlier = [name for name in OUTPUT_FILES if (output_dir / name).exists()]
    if earlier and not overwrite:
        raise FileExistsError(
            f"--output_dir {str(output_dir)!r} already holds {', '.join(earlier)} from an earlier run; choose another "
            "--output_dir, or pass --overwrite true to replace them"
        )


# The lock a run holds in its output folder while it runs (removed when it ends).
LOCK_FILE = ".enmi-fit-mask.lock"


class OutputClaim:
    """An output folder this run holds alone until :meth:`release`: an exclusive lock no other run can take at once.

    The lock (``flock`` on :data:`LOCK_FILE`) goes with the process, so a run killed by SIGKILL leaves no stale claim;
    the folder's earlier files are judged only once it is held (:func:`check_output_dir`), so two runs started at once
    cannot both find it free. Folders made for the claim are removed again by a run that wrote nothing there.
    """

    def __init__(self, folder: Path, descriptor: int, created: list[Path]) -> None:
        self.folder, self._descriptor, self._created = folder, descriptor, created

    def release(self) -> None:
        """Give the folder back (removing the lock file, and the folders made for it if they stayed empty)."""
        if self._descriptor < 0:
            return
        with contextlib.suppress(OSError):
            (self.folder / LOCK_FILE).unlink()
        os.close(self._descriptor)  # closing drops the lock
        self._descriptor = -1
        for folder in self._created:  # deepest first; a folder that holds anything stays
            with contextlib.suppress(OSError):
                folder.rmdir()


def claim_output_dir(output_dir: Path, overwrite: bool, option: str = "--output_dir") -> OutputClaim:
    """Take ``output_dir`` for this run, atomically, then refuse it if it holds an earlier run's files.

    Raises ``ValueError`` if another run holds it now (started at once with the same folder), naming ``option``; the
    earlier files: ``FileExistsError`` unless ``overwrite`` (:func:`check_output_dir`).
    """
    import fcntl

    check_folder_to_write(output_dir, option)
    created = [folder for folder in (output_dir, *output_dir.absolute().parents) if not folder.exists()]
    output_dir.mkdir(parents=True, exist_ok=True)
    lock = output_dir / LOCK_FILE
    while True:
        descriptor = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(descriptor)
            raise ValueError(
                f"{option} {str(output_dir)!r} is being written by another run (started at the same time or earlier, "
                f"still running): choose another {option}, or start this one when that run has ended"
            ) from None
        try:  # the file locked must still be the lock: a run that just ended removes its file
            if os.fstat(descriptor).st_ino == os.stat(lock).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(descriptor)
    claim = OutputClaim(output_dir, descriptor, [folder for folder in created if folder != Path(".")])
    try:
        check_output_dir(output_dir, overwrite)
    except BaseException:
        claim.release()
        raise
    return claim


# Which of the model's options take effect under which values of the others (see enmi_torch.utils.options).
MASK_RULES = (
    OptionRule("degree", "form", ("radial",), "the degree of the radial form's polynomial"),
    OptionRule("analytic_variance", "form", ("perspective",), "the analytic map of the perspective form"),
)
# The held-out search of the dashboards needs this many pixels per side of each searched crop at least.
MIN_SEARCHED_SIDE = 1


def check_model_options(options: Mapping[str, Any], defaults: Mapping[str, Any]) -> None:
    """Check every option of :class:`~enmi_torch.training.mask_module.MaskFitModule` (and :data:`MASK_RULES`).

    Each message names the option (``lr must be a finite number > 0, got -1.0``), so that a fit stops before it
    starts, not at the first optimiser step or validation; the held-out search's size against the images is
    :func:`check_held_out_search`. ``defaults``: the constructor's.
    """
    check_image_shape("shape", options["shape"])
    check_positive_number("lr", options["lr"])
    smoothness = options["smoothness"]
    if isinstance(smoothness, bool) or not isinstance(smoothness, (int, float)) or not 0 <= smoothness < math.inf:
        raise ValueError(f"smoothness must be a finite number >= 0, got {smoothness!r}")
    check_non_negative_int("degree", options["degree"])
    check_bool("match_intensity", options["match_intensity"])
    check_bins(options["bins"])
    check_value_range(options["value_range"])
    check_non_negative_int("localization_pairs", options["localization_pairs"])
    check_positive_int("localization_shift", options["localization_shift"])  # 0 searches one shift: every pair a hit
    check_positive_int("localization_crop", options["localization_crop"])
    for name in ("localization_noise", "localization_grid"):
        factors = options[name]
        if name == "localization_noise" and factors is None:
            continue  # the held-out levels are read from the held-out pairs
        if not all(
            isinstance(factor, (int, float)) and not isinstance(factor, bool) and 0 < factor < math.inf
            for factor in factors
        ) or (name == "localization_noise" and not factors):
            what = "null (levels read from the data) or " if name == "localization_noise" else ""
            raise ValueError(f"{name} must be {what}finite factors > 0, got {list(factors)}")
        if len({float(factor) for factor in factors}) < len(factors):
            raise ValueError(f"{name} must be distinct factors, got {list(factors)}")
    analytic = options["analytic_variance"]
    if analytic is not None and Path(analytic).is_dir():
        raise ValueError(f"analytic_variance must name an .npy file, got the folder {str(analytic)!r}")
    check_option_rules(MASK_RULES, options, defaults)
    check_held_out_search(options)


def check_held_out_search(options: Mapping[str, Any]) -> None:
    """Refuse images too small for the held-out search, naming their size and the options that set the search.

    Each held-out pair is searched on its central square of up to ``localization_crop`` pixels, inside a border of
    ``localization_shift`` pixels on each side, within the ``shape`` of the images: at least :data:`MIN_SEARCHED_SIDE`
    pixels must be left to search. Raises :class:`~enmi_torch.utils.options.OptionError` (the command spells each
    option as its flag).
    """
    if options["localization_pairs"] == 0:
        return
    height, width = options["shape"]
    shift, crop = options["localization_shift"], options["localization_crop"]
    searched = min(crop + 2 * shift, height, width) - 2 * shift
    if searched >= MIN_SEARCHED_SIDE:
        return
    largest = (min(height, width) - MIN_SEARCHED_SIDE) // 2

    def write(spell: Callable[[str, Any], str]) -> str:
        remedy = f"pass {spell('localization_shift', largest)} or less, or " if largest >= 1 else "pass "
        return (
            f"the pairs are {height}x{width} pixels: too small for the held-out search, which searches a crop of up "
            f"to {spell('localization_crop', crop)} pixels inside a border of {spell('localization_shift', shift)} "
            f"pixels on each side; {remedy}{spell('localization_pairs', 0)} (no held-out search)"
        )

    raise OptionError(write)


def check_learnable(datamodule: PairDataModule, data: Mapping[str, Any]) -> None:
    """Refuse pairs in which no pixel is valid in two training pairs (nothing to learn a variance from).

    Reads the training pairs' valid masks until one pixel is valid in two of them (two pairs, as a rule; every pair
    where none is, the pass the fit would make anyway). ``data``: the command's ``--data`` options, for the message.
    """
    pairs = datamodule.train_set
    seen = None
    for index in range(len(pairs)):
        valid = pairs[index]["valid"].reshape(-1).to(torch.int32)
        seen = valid if seen is None else seen + valid
        if bool((seen >= 2).any()):
            return
    problem = "no pixel is valid in two training pairs or more: nothing to learn a variance from"
    if data.get("root") is None:
        raise ValueError(f"--data.train_pairs {len(pairs)}: {problem}; pass --data.train_pairs 2 or more")
    held_out = len(datamodule.val_set)
    raise ValueError(
        f"--data.root {data['root']} holds {len(pairs) + held_out} pair(s), {held_out} held out "
        f"(--data.val_fraction {data.get('val_fraction')}) and {len(pairs)} to train on: {problem}; "
        + ("give it more pairs" if len(pairs) < 2 else "their valid/ masks must overlap")
    )
