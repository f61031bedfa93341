"""Local/prior image pairs on disk: the folder format, a lazy dataset over it, and a writer.

Format (one folder)::

    pairs/
      meta.json          {"format": "enmi_torch.pairs", "version": 1, "shape": [H, W]}  (optional, see below)
      local/<name>.npy   local (captured) image, (H, W), or .png (8- or 16-bit grey)
      prior/<name>.npy   the prior-map section that matches it, same name (stem), .npy or .png
      valid/<name>.npy   optional, bool (or 0/1, or a grey .png: non-zero = valid) map of the pixels in range

Pairs are matched by file stem; every ``local`` needs a ``prior`` partner (and a ``valid`` one when the ``valid/``
folder exists), and no partner may be left over. ``.npy`` files are read with ``allow_pickle=False``. ``meta.json``
may also give ``"truth": {"variance": "truth_variance.npy"}`` (a known variance map, NaN where invalid, as the
synthetic generator writes) and free-form ``"source"`` text; without ``meta.json`` the shape is the first local
image's. Files are read only when an item is asked for, so datasets far larger than memory stream from disk.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from enmi_torch.data.truth import VarianceTruth
from enmi_torch.utils.checks import check_image_shape, check_option
from enmi_torch.utils.files import read_image, read_json

PAIR_FORMAT = "enmi_torch.pairs"
PAIR_VERSION = 1
IMAGE_SUFFIXES = (".npy", ".png")
FOLDERS = ("local", "prior", "valid")


class PairDataset(Dataset):
    """The pairs of a folder in the format above, read lazily.

    Args:
        root: the folder.

    Items are dicts: ``local`` and ``prior`` ``(1, H, W)`` float32, ``valid`` ``(1, H, W)`` bool (all ``True``
    without a ``valid/`` folder), ``index`` int. A missing partner, a duplicated name, a bad ``meta.json`` raise
    ``ValueError`` at construction; an unreadable file, a shape mismatch or a NaN at a valid pixel raise
    ``ValueError`` naming the file when the item is read.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"root must be a folder of pairs (local/, prior/, ...), got {str(self.root)!r}")
        meta = _read_meta(self.root / "meta.json")
        files = {folder: _list_images(self.root / folder) for folder in FOLDERS}
        if not files["local"]:
            raise ValueError(f"{self.root / 'local'} holds no .npy or .png image")
        partners = ("prior", "valid") if (self.root / "valid").is_dir() else ("prior",)
        for folder in partners:
            _check_partners(self.root, files["local"], files[folder], folder)
        self.names = sorted(files["local"])
        self._files = {folder: files[folder] for folder in ("local", *partners)}
        self.shape = (
            check_image_shape(f"{self.root / 'meta.json'} shape", meta["shape"])
            if "shape" in meta
            else tuple(_read_image(self._files["local"][self.names[0]]).shape)
        )
        self.truth = _read_truth(self.root, meta.get("truth"), self.shape)

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: int) -> dict:
        name = self.names[index]
        local = self._read(self._files["local"][name]).astype(np.float32)
        prior = self._read(self._files["prior"][name]).astype(np.float32)
        if "valid" in self._files:
            valid = self._read(self._files["valid"][name], as_mask=True)
        else:
            valid = np.ones(self.shape, dtype=bool)
        for path, image in ((self._files["local"][name], local), (self._files["prior"][name], prior)):
            bad = valid & ~np.isfinite(image)
            if bad.any():
                raise ValueError(f"{path} holds {int(bad.sum())} NaN/inf value(s) at valid pixels")
        return {
            "local": torch.from_numpy(local).unsqueeze(0),
            "prior": torch.from_numpy(prior).unsqueeze(0),
            "valid": torch.from_numpy(valid).unsqueeze(0),
            "index": index % len(self),
        }

    def _read(self, path: Path, *, as_mask: bool = False) -> np.ndarray:
        image = _read_image(path, as_mask=as_mask)
        if image.shape != self.shape:
            raise ValueError(f"{path} has shape {image.shape}, expected {self.shape} like the other images")
        return image


def _read_meta(path: Path) -> dict:
    if not path.is_file():
        return {}
    meta = read_json(path, "meta.json")
    if not isinstance(meta, dict) or meta.get("format") != PAIR_FORMAT or meta.get("version") != PAIR_VERSION:
        raise ValueError(f"{path} must be a JSON object with format {PAIR_FORMAT!r} and version {PAIR_VERSION}")
    return meta


def _read_truth(root: Path, truth: object, shape: tuple[int, int]) -> VarianceTruth | None:
    if truth is None:
        return None
    if not isinstance(truth, dict) or not isinstance(truth.get("variance"), str):
        raise ValueError(f"{root / 'meta.json'} truth must be {{'variance': 'FILE.npy'}}, got {truth!r}")
    path = root / truth["variance"]
    variance = _read_image(path, source="meta.json truth variance")
    if variance.shape != shape:
        raise ValueError(f"{path} has shape {variance.shape}, expected {shape} like the images")
    valid = np.isfinite(variance)
    try:
        return VarianceTruth(torch.from_numpy(variance.astype(np.float64)), torch.from_numpy(valid), "file")
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def _list_images(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        return {}
    files: dict[str, Path] = {}
    for path in sorted(folder.iterdir()):
        if path.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        if path.stem in files:
            raise ValueError(f"{files[path.stem]} and {path} have the same name; keep one image per name")
        files[path.stem] = path
    return files


def _check_partners(root: Path, local: dict[str, Path], other: dict[str, Path], folder: str) -> None:
    if not (root / folder).is_dir():
        raise ValueError(f"{root / folder} is missing: every local image needs a {folder} partner")
    for source, target, target_folder in ((local, other, folder), (other, local, "local")):
        missing = sorted(set(source) - set(target))
        if missing:
            shown = ", ".join(str(source[name]) for name in missing[:3])
            more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
            raise ValueError(
                f"{shown}{more} ha{'s' if len(missing) == 1 else 've'} no partner in {root / target_folder} "
                f"(expected the same name with .npy or .png)"
            )


def _read_image(path: Path, *, as_mask: bool = False, source: str = "pair image") -> np.ndarray:
    """A single-channel ``(H, W)`` array from ``.npy`` (no pickles) or a grey ``.png``; bool when ``as_mask``.

    ``source`` names the file's role in messages.
    """
    image = read_image(path, source)
    if as_mask:
        if image.dtype != bool and image.dtype.kind not in "iu":
            raise ValueError(f"{path} must hold a bool or integer mask, got dtype {image.dtype}")
        return image != 0
    if image.dtype.kind not in "fiub":
        raise ValueError(f"{path} must hold numbers, got dtype {image.dtype}")
    return image


def write_pairs(
    root: str | Path,
    pairs: Iterable[dict],
    *,
    image_format: str = "npy",
    truth: VarianceTruth | None = None,
    source: str = "",
) -> int:
    """Write ``pairs`` (items like :class:`PairDataset`'s) into a new folder ``root`` in the format above.

    Args:
        root: the folder; it must not exist yet or be empty.
        pairs: dicts with ``local``, ``prior``, ``valid`` ``(1, H, W)`` or ``(H, W)`` tensors or arrays.
        image_format: ``"npy"`` (float32, exact) or ``"png"`` (8-bit: values rounded and clipped to ``[0, 255]``,
            which adds about 1/12 to the noise variance and clips it near black and white).
        truth: written as ``truth_variance.npy`` and named in ``meta.json`` when given.
        source: free text for ``meta.json``.

    Returns:
        The number of pairs written; their names are ``000000``, ``000001``, ...
    """
    check_option("image_format", image_format, ("npy", "png"))
    root = Path(root)
    if root.exists() and any(root.iterdir()):
        raise ValueError(f"root must be a new or empty folder, got {str(root)!r} which holds files")
    for folder in FOLDERS:
        (root / folder).mkdir(parents=True, exist_ok=True)
    shape = None
    count = 0
    for count, pair in enumerate(pairs, start=1):
        name = f"{count - 1:06d}"
        for folder in FOLDERS:
            image = np.asarray(pair[folder]).reshape(np.asarray(pair[folder]).shape[-2:])
            shape = shape or image.shape
            if image.shape != shape:
                raise ValueError(f"pair {name} {folder} has shape {image.shape}, expected {shape}")
            _write_image(root / folder / name, image, image_format, is_mask=folder == "valid")
    if shape is None:
        raise ValueError("pairs must hold at least one pair, got none")
    meta = {"format": PAIR_FORMAT, "version": PAIR_VERSION, "shape": list(shape), "source": source}
    if truth is not None:
        np.save(root / "truth_variance.npy", truth.variance.numpy(), allow_pickle=False)
        meta["truth"] = {"variance": "truth_variance.npy"}
    (root / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return count


def _write_image(stem: Path, image: np.ndarray, image_format: str, *, is_mask: bool) -> None:
    if image_format == "npy":
        np.save(stem.with_suffix(".npy"), image.astype(bool if is_mask else np.float32), allow_pickle=False)
        return
    from PIL import Image

    grey = (image != 0) * 255 if is_mask else np.clip(np.rint(image), 0, 255)
    Image.fromarray(grey.astype(np.uint8)).save(stem.with_suffix(".png"))
