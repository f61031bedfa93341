"""Synthetic local/prior pairs: prior maps cut from real road-like imagery, locals = prior + noise of known variance.

Prior patches come from scikit-image's bundled ``gravel()`` texture (CC0, shipped with the package: nothing is
downloaded) with painted lane markings; the local image is the same patch, optionally with a global intensity change,
plus Gaussian noise drawn from a :class:`~enmi_torch.data.truth.VarianceTruth`. Pair ``i`` is a pure function of
``(seed, i)``, so a dataset of any length costs no memory, every worker and process sees the same pairs, and runs
are reproducible. :class:`KeptPairs` generates them once and keeps them in memory, for training over many epochs.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch.utils.data import Dataset

from enmi_torch.data.truth import VarianceTruth, check_std
from enmi_torch.utils.checks import check_non_negative_int, check_positive_int


@functools.cache
def gravel_texture() -> np.ndarray:
    """scikit-image's ``gravel()`` (512 x 512, CC0) as float32 grey levels in ``[0, 255]``."""
    try:
        from skimage import data
    except ImportError as error:
        raise ImportError(
            "the synthetic pairs need scikit-image for its bundled gravel() texture: pip install 'enmi_torch[train]'"
        ) from error
    texture = data.gravel().astype(np.float32)
    texture.setflags(write=False)
    return texture


def road_patch(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """A ``(H, W)`` float32 patch of road: a random crop of :func:`gravel_texture` with painted lane markings.

    The crop is turned by a random multiple of 90 degrees and mirrored at random; one to three roughly vertical
    markings (the vehicle heads up) are painted on it, solid or dashed, anti-aliased.
    """
    texture = gravel_texture()
    height, width = shape
    if height > texture.shape[0] or width > texture.shape[1]:
        raise ValueError(f"shape must fit in the {texture.shape} texture, got {shape}")
    texture = np.rot90(texture, int(rng.integers(4)))
    if rng.random() < 0.5:
        texture = texture[:, ::-1]
    top = int(rng.integers(texture.shape[0] - height + 1))
    left = int(rng.integers(texture.shape[1] - width + 1))
    patch = np.array(texture[top : top + height, left : left + width], dtype=np.float32)
    rows = np.arange(height, dtype=np.float32)[:, None]
    cols = np.arange(width, dtype=np.float32)[None, :]
    for _ in range(int(rng.integers(1, 4))):
        _paint_marking(patch, rng, rows, cols)
    return patch


def _paint_marking(patch: np.ndarray, rng: np.random.Generator, rows: np.ndarray, cols: np.ndarray) -> None:
    height, width = patch.shape
    angle = math.radians(rng.uniform(-12.0, 12.0))
    column = rng.uniform(0.1, 0.9) * width
    half_width = rng.uniform(1.0, 3.5)
    # Only the columns the marking can touch are painted (the others would get coverage 0): the same values, at
    # most a third of a 128-pixel-wide patch. The band's bound is that of |across| < half_width + 0.5, plus 2 pixels.
    reach = (abs(height / 2 * math.sin(angle)) + half_width + 0.5) / math.cos(angle) + 2
    first, last = max(0, math.floor(column - reach)), min(width, math.ceil(column + reach) + 1)
    patch, cols = patch[:, first:last], cols[:, first:last]
    # Signed distance across the marking and position along it, for a line through (height / 2, column).
    across = (cols - column) * math.cos(angle) - (rows - height / 2) * math.sin(angle)
    along = (cols - column) * math.sin(angle) + (rows - height / 2) * math.cos(angle)
    coverage = np.clip(half_width + 0.5 - np.abs(across), 0.0, 1.0)
    if rng.random() < 0.5:
        period = rng.uniform(0.3, 0.6) * height
        dash = rng.uniform(0.4, 0.7) * period
        coverage = coverage * (np.mod(along + rng.uniform(0, period), period) < dash)
    paint = rng.uniform(200.0, 245.0)
    patch += coverage * (paint - patch)


class SyntheticPairs(Dataset):
    """``count`` local/prior pairs drawn on the fly, with the noise variance field ``truth``.

    Args:
        truth: the noise variance field (its shape is the image shape); pixels outside ``truth.valid`` are out of
            the sensor's range: the local image holds 0 there and the pair's valid map is ``False``.
        count: number of pairs.
        seed: pairs ``i`` of two datasets with the same seed are equal; use different seeds for train and held-out.
        gain_std: std of a per-pair intensity gain ``1 + N(0, gain_std^2)`` applied to the local image.
        offset_std: std of a per-pair intensity offset ``N(0, offset_std^2)`` added to the local image.

    Items are dicts: ``local`` and ``prior`` ``(1, H, W)`` float32, ``valid`` ``(1, H, W)`` bool, ``index`` int.

    Example:
        >>> from enmi_torch.data.truth import lidar_truth
        >>> pairs = SyntheticPairs(lidar_truth((32, 32)), count=4)
        >>> item = pairs[0]
        >>> item["local"].shape, item["valid"].dtype, len(pairs)
        (torch.Size([1, 32, 32]), torch.bool, 4)
        >>> bool((pairs[0]["local"] == item["local"]).all())
        True
    """

    def __init__(
        self, truth: VarianceTruth, count: int, *, seed: int = 0, gain_std: float = 0.0, offset_std: float = 0.0
    ) -> None:
        if not isinstance(truth, VarianceTruth):
            raise TypeError(f"truth must be a VarianceTruth, got {type(truth).__name__}")
        self.truth = truth
        self.count = check_positive_int("count", count)
        self.seed = check_non_negative_int("seed", seed)
        self.gain_std, self.offset_std = check_std("gain_std", gain_std), check_std("offset_std", offset_std)
        texture_shape = gravel_texture().shape
        if truth.shape[0] > texture_shape[0] or truth.shape[1] > texture_shape[1]:
            raise ValueError(f"truth must be at most {texture_shape} (the gravel texture), got shape {truth.shape}")
        valid = truth.valid.numpy()
        self._valid = valid
        self._std = np.sqrt(np.where(valid, truth.variance.numpy(), 0.0)).astype(np.float32)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the images."""
        return self.truth.shape

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int) -> dict:
        if not -self.count <= index < self.count:
            raise IndexError(f"index must be in [-{self.count}, {self.count}), got {index}")
        index = index % self.count
        rng = np.random.default_rng((self.seed, index))
        prior = road_patch(rng, self.shape)
        gain = 1.0 + self.gain_std * rng.standard_normal() if self.gain_std else 1.0
        offset = self.offset_std * rng.standard_normal() if self.offset_std else 0.0
        noise = rng.standard_normal(self.shape, dtype=np.float32) * self._std
        local = np.where(self._valid, gain * prior + offset + noise, 0.0).astype(np.float32)
        return {
            "local": torch.from_numpy(local).unsqueeze(0),
            "prior": torch.from_numpy(prior).unsqueeze(0),
            "valid": torch.from_numpy(self._valid.copy()).unsqueeze(0),
            "index": index,
        }


class KeptPairs(Dataset):
    """The items of ``pairs`` read once and kept in memory as stacked tensors: item ``i`` equals ``pairs[i]``.

    Reading a :class:`SyntheticPairs` item draws the pair again (a crop, lane markings, noise); over many epochs of
    the same pairs, keeping them costs ``9 H W`` bytes per pair (2,000 pairs of 128 x 128: 0.3 GB) and saves that
    work.

    Args:
        pairs: a dataset whose items are dicts like :class:`SyntheticPairs`'s (``local``, ``prior``, ``valid``,
            ``index``); its ``truth`` and ``shape`` are kept when it has them.

    Example:
        >>> from enmi_torch.data.truth import lidar_truth
        >>> pairs = SyntheticPairs(lidar_truth((32, 32)), count=4, seed=3)
        >>> kept = KeptPairs(pairs)
        >>> all(torch.equal(kept[2][key], pairs[2][key]) for key in ("local", "prior", "valid")), kept[2]["index"]
        (True, 2)
    """

    def __init__(self, pairs: Dataset) -> None:
        count = len(pairs)
        if count < 1:
            raise ValueError(f"pairs must hold at least one pair, got {count}")
        self.truth = getattr(pairs, "truth", None)
        self.indices: list[int] = []
        for position in range(count):
            item = pairs[position]
            if position == 0:
                # Filled in place: no list of items and stacked copy at the same time.
                self.local = torch.empty((count, *item["local"].shape), dtype=item["local"].dtype)
                self.prior = torch.empty((count, *item["prior"].shape), dtype=item["prior"].dtype)
                self.valid = torch.empty((count, *item["valid"].shape), dtype=item["valid"].dtype)
            self.local[position], self.prior[position], self.valid[position] = (
                item["local"],
                item["prior"],
                item["valid"],
            )
            self.indices.append(int(item["index"]))

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the images."""
        return tuple(self.local.shape[-2:])

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index: int) -> dict:
        return {
            "local": self.local[index],
            "prior": self.prior[index],
            "valid": self.valid[index],
            "index": self.indices[index],
        }
