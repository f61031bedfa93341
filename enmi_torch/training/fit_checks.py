"""What the fit-mask command checks before it trains: the checkpoint, the output folder, the pairs.

Each raises a ``ValueError`` (or ``FileNotFoundError``, ``FileExistsError``) naming the option as the command line
spells it, before any of Lightning's lines.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from pathlib import Path

import torch
from torch.utils.data import Subset

from enmi_torch.data import PairDataModule
from enmi_torch.data.pairs import PairDataset
from enmi_torch.utils.files import load_plain_torch

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
