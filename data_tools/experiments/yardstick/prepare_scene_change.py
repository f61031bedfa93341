"""Turn downloaded copies of public scene-change datasets into the yardstick's co-registered pair folders.

Usage:
    python -m data_tools.experiments.yardstick.prepare_scene_change --dataset levir-cd --source DIR \
        --out DIR [--correct]

Each pair becomes ``OUT/<case>/<dataset>-<id>/`` with ``reference.npy`` (the map: the older date, the street-map
rendering, the optical image) and ``captured.npy`` (the other date or modality), both grey float32 in [0, 255] and of
one shape, ``changed.npy`` (bool, where the source marks change, when it does) and ``meta.json`` (source, licence,
how the pair is registered, the measured residual offset). ``OUT/manifest.json`` lists every folder under OUT
and the pairs rejected. ``<case>`` is ``another-date`` or ``another-modality``.

Every pair is checked by measurement: a similarity of the two images over integer shifts of +-6 pixels (changed
pixels left out where the source marks them), refined to sub-pixel by a parabola: the normalised cross-correlation
of the gradient magnitudes for two photographs (another date), the normalised mutual information of the grey levels
for two modalities, where a map's or a SAR image's grey levels bear no monotone relation to the photograph's; on the
whole image and on overlapping 96 x 96 tiles (those with a clear peak). A pair is kept when the whole-image peak and
the median of at least 3 tiles both lie within ``--tolerance`` pixels (0.5) of (0, 0) on both axes, and an affine
field fitted to the tiles' offsets (where >= 6 tiles agree) moves by at most twice the tolerance between the image's
centre and its corners, less two standard errors (a rotation or scale error left by a registration grows there); the
tiles' spread (scaled median absolute deviation) is recorded, not judged. With ``--correct``, a pair whose
whole-image and tile estimates agree on one larger offset is shifted by that offset rounded to whole pixels (both
images cropped, no resampling) and measured again. With ``--tile N`` each pair is first cut into non-overlapping
N x N tiles (``<id>_<row>_<col>``, as the datasets' published 256 x 256 crops are), each measured and kept on its
own: a relief displacement that differs between dates, or a changed quarter, then costs its tiles, not the image.

Datasets (``--dataset``), what ``--source`` must hold, where each is published and its terms as the source states:

* ``levir-cd``, ``dsifn-cd`` (another date): a folder with ``A/``, ``B/`` and ``label/`` holding same-named images
  (the published layout; the ChangeFormer repository's ``samples_LEVIR`` and ``samples_DSIFN`` too). LEVIR-CD:
  https://justchenhao.github.io/LEVIR/ (Google Earth images, 0.5 m; no licence in the copies read here).
  DSIFN-CD: github.com/GeoZcx/A-deeply-supervised-image-fusion-network-for-change-detection-in-remote-sensing-images
  (Google Earth images of six Chinese cities; no licence stated). A is the reference, B the captured image.
* ``whu-cd`` (another date): the same layout, or ``prev/``, ``curr/`` and ``label/`` (the UCD-SCM repository's
  ``data/samples_WHU-CD``, github.com/StephenApX/UCD-SCM). WHU-CD (WHU building change detection,
  https://study.rsgis.whu.edu.cn/pages/download/building_dataset.html): aerial photographs of Christchurch, 2012 and
  2016, 0.3 m (Ji, Wei and Lu, TGRS 2019; no licence in the copy read). The earlier date is the reference.
* ``oscd`` (another date): the ``Onera Satellite Change Detection dataset - Images`` folder (one folder per city
  with ``imgs_1/``, ``imgs_2/`` holding the Sentinel-2 bands ``*_B02/B03/B04.tif``; change maps ``cm/cm.png`` there
  or in the sibling ``... - Train Labels`` folder, optional), https://rcdaudt.github.io/oscd/ : "modified Copernicus
  data from 2015-2018" (free and open Copernicus Sentinel data), change maps CC BY-NC-SA. 10 m pixels, registered
  with GeFolki by the authors. The grey image is the luma of B04/B03/B02 stretched between its 0.5 and 99.5
  percentiles.
* ``pix2pix-maps`` (another modality): 1200 x 600 jpgs holding a satellite photograph (left half) beside its Google
  Maps rendering (right half), the pix2pix ``maps`` set (https://efrosgans.eecs.berkeley.edu/pix2pix/datasets/,
  scraped from Google Maps; no licence stated, Google's terms apply), or a pix2pix test run's ``N_real_A.png`` /
  ``N_real_B.png`` images of it (256 x 256). The rendering is the reference.
* ``srif-optical-map``, ``srif-optical-sar``, ``srif-optical-infrared`` (another modality) and
  ``srif-optical-optical`` (another date): the ``dataset/`` folder of https://github.com/LJY-RS/SRIF (Li, Hu and
  Zhang, ISPRS J. 2023; no licence stated, the README asks for a citation). Each ``pairN_1.jpg`` / ``pairN_2.jpg``
  comes with ``gt_N.txt``, the 2 x 3 similarity that maps (1-based) pixels of the first image into the second. One
  image is resampled (cubic, anti-aliased when shrunk) into the other's frame, the frame whose largest fully covered
  rectangle holds more ground (the coarser frame on a tie), and both are cropped to that rectangle. The first image
  (optical) is the reference, except for ``srif-optical-map`` where the map rendering is. The given similarities
  are off by up to ~5 px: most pairs need ``--correct``.
* ``cfog`` (another modality): a checkout of https://github.com/yeyuanxin110/CFOG (Ye et al., TGRS 2019: "for
  research purposes only. Any commercial use is prohibited"): optical against SAR, lidar depth, lidar intensity,
  infrared and a map, 500-1000 pixels. An affine map (least squares) from the reference image to the sensed one is
  fitted to the control points shipped with each pair; the sensed image is resampled into the reference frame. The
  map (where there is one), else the optical image, is the yardstick's reference.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage

CASES = {"date": "another-date", "modality": "another-modality"}
LUMA = np.array([0.299, 0.587, 0.114])
MIN_SIDE = 150


@dataclass
class Pair:
    """One co-registered pair as a reader yields it (grey float64 in [0, 255], one shape)."""

    name: str
    reference: np.ndarray
    captured: np.ndarray
    meta: dict
    changed: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)


def read_grey(path: Path) -> np.ndarray:
    """Grey float64 image in [0, 255] of an 8-bit file (luma of RGB), by Pillow or tifffile."""
    try:
        with Image.open(path) as image:
            array = np.asarray(image.convert("RGB") if image.mode in ("P", "RGBA", "LA", "CMYK") else image)
    except Exception:  # Pillow cannot read some multi-band tiffs
        import tifffile

        array = tifffile.imread(path)
    array = array.astype(np.float64)
    if array.ndim == 3:
        array = array[..., :3] @ LUMA if array.shape[-1] >= 3 else array[..., 0]
    if array.max() > 255:
        raise ValueError(f"{path}: expected an 8-bit image, got values up to {array.max():g}")
    return array


def stretch(array: np.ndarray) -> np.ndarray:
    """Map the 0.5 and 99.5 percentiles to 0 and 255 and clip."""
    low, high = np.percentile(array, [0.5, 99.5])
    return np.clip((array - low) * 255.0 / max(high - low, 1e-9), 0.0, 255.0)


def gradient_magnitude(image: np.ndarray, sigma: float = 1.0) -> np.ndarray:
    smooth = ndimage.gaussian_filter(image, sigma)
    return np.hypot(ndimage.sobel(smooth, 0), ndimage.sobel(smooth, 1))


def ncc_surface(reference: np.ndarray, captured: np.ndarray, valid: np.ndarray, radius: int) -> np.ndarray:
    """NCC over ``valid`` of ``reference`` against ``captured`` moved by (dy, dx) in [-radius, radius]^2."""
    height, width = reference.shape
    inner = (slice(radius, height - radius), slice(radius, width - radius))
    keep = valid[inner]
    core = reference[inner][keep]
    core = (core - core.mean()) / (core.std() + 1e-12)
    surface = np.empty((2 * radius + 1, 2 * radius + 1))
    for i, dy in enumerate(range(-radius, radius + 1)):
        for j, dx in enumerate(range(-radius, radius + 1)):
            moved = captured[radius + dy : height - radius + dy, radius + dx : width - radius + dx][keep]
            surface[i, j] = np.mean(core * (moved - moved.mean()) / (moved.std() + 1e-12))
    return surface


def surface_peak(surface: np.ndarray) -> tuple[float, float, float, float, bool]:
    """Sub-pixel (dy, dx) of the maximum, its value, its margin over the best value >= 3 px away, on the edge."""
    radius = surface.shape[0] // 2
    i, j = np.unravel_index(np.argmax(surface), surface.shape)
    edge = i in (0, 2 * radius) or j in (0, 2 * radius)
    offsets = [0.0, 0.0]
    if not edge:
        for axis, (low, mid, high) in enumerate(
            (
                (surface[i - 1, j], surface[i, j], surface[i + 1, j]),
                (surface[i, j - 1], surface[i, j], surface[i, j + 1]),
            )
        ):
            curvature = low - 2 * mid + high
            offsets[axis] = 0.5 * (low - high) / curvature if curvature < 0 else 0.0
    far = np.ones_like(surface, dtype=bool)
    far[max(i - 2, 0) : i + 3, max(j - 2, 0) : j + 3] = False
    return i - radius + offsets[0], j - radius + offsets[1], surface[i, j], surface[i, j] - surface[far].max(), edge


def nmi_surface(reference: np.ndarray, captured: np.ndarray, valid: np.ndarray, radius: int, bins: int) -> np.ndarray:
    """(H(A) + H(B)) / H(A, B) over ``valid``, hard bins over [0, 256), ``captured`` moved by (dy, dx) as above."""
    height, width = reference.shape
    inner = (slice(radius, height - radius), slice(radius, width - radius))
    keep = valid[inner]
    reference_bins = np.clip((reference[inner][keep] * bins / 256.0).astype(int), 0, bins - 1) * bins
    captured_bins = np.clip((captured * bins / 256.0).astype(int), 0, bins - 1)

    def entropy(counts: np.ndarray) -> float:
        probability = counts[counts > 0] / counts.sum()
        return float(-(probability * np.log(probability)).sum())

    surface = np.empty((2 * radius + 1, 2 * radius + 1))
    for i, dy in enumerate(range(-radius, radius + 1)):
        for j, dx in enumerate(range(-radius, radius + 1)):
            moved = captured_bins[radius + dy : height - radius + dy, radius + dx : width - radius + dx][keep]
            joint = np.bincount(reference_bins + moved, minlength=bins * bins).reshape(bins, bins)
            surface[i, j] = (entropy(joint.sum(1)) + entropy(joint.sum(0))) / entropy(joint.ravel())
    return surface


SCORES = {
    "gradient-ncc": "NCC of gradient magnitudes (Gaussian sigma 1, Sobel)",
    "nmi": "normalised mutual information of the grey levels (32 bins on the whole image, 16 on tiles)",
}


def measure_offset(
    reference: np.ndarray,
    captured: np.ndarray,
    changed: np.ndarray | None = None,
    score: str = "gradient-ncc",
    radius: int = 6,
    tile: int = 96,
) -> dict:
    """Where the captured image's content sits relative to the reference's, in pixels (dy, dx); (0, 0) = aligned.

    A positive dy means a feature at row r of the reference is at row r + dy of the captured image. ``score`` is
    ``"gradient-ncc"`` (two photographs) or ``"nmi"`` (two modalities, where grey levels map non-linearly).
    """
    valid = np.ones(reference.shape, bool) if changed is None else ~ndimage.binary_dilation(changed, iterations=4)
    if score == "gradient-ncc":
        first, second = gradient_magnitude(reference), gradient_magnitude(captured)

        def surface_of(box, bins):
            return ncc_surface(first[box], second[box], valid[box], radius)
    else:
        first, second = reference, captured

        def surface_of(box, bins):
            return nmi_surface(first[box], second[box], valid[box], radius, bins)

    whole = (slice(None), slice(None))
    dy, dx, peak, margin, edge = surface_peak(surface_of(whole, 32))
    tiles = []
    for top in range(0, reference.shape[0] - tile + 1, tile // 2):
        for left in range(0, reference.shape[1] - tile + 1, tile // 2):
            box = (slice(top, top + tile), slice(left, left + tile))
            if valid[box].mean() < 0.6:
                continue
            surface = surface_of(box, 16)
            tile_dy, tile_dx, tile_peak, tile_margin, tile_edge = surface_peak(surface)
            clear = (
                tile_margin >= 0.02 and tile_peak >= 0.1
                if score == "gradient-ncc"
                else (tile_margin >= 0.15 * (tile_peak - np.median(surface)))
            )
            if not tile_edge and clear:
                tiles.append((tile_dy, tile_dx, top + tile / 2, left + tile / 2))
    result = {
        "method": f"{SCORES[score]}, shifts +-{radius} px, parabolic peak",
        "whole_image_offset_dy_dx": [round(float(dy), 2), round(float(dx), 2)],
        "whole_image_peak": round(float(peak), 4),
        "whole_image_peak_margin": round(float(margin), 4),
        "whole_image_peak_on_edge": bool(edge),
        "tiles_agreeing": len(tiles),
        "tile_size": tile,
    }
    if tiles:
        shifts, centres = np.array(tiles)[:, :2], np.array(tiles)[:, 2:]
        median = np.median(shifts, axis=0)
        result["tiles_median_offset_dy_dx"] = [round(float(value), 2) for value in median]
        result["tiles_spread_dy_dx"] = [round(float(v), 2) for v in 1.4826 * np.median(abs(shifts - median), 0)]
        if len(tiles) >= 6:
            corner, error = affine_corner_deviation(shifts, centres, reference.shape)
            result["tiles_affine_corner_deviation"] = round(corner, 2)
            result["tiles_affine_corner_deviation_error"] = round(error, 2)
    return result


def affine_corner_deviation(shifts: np.ndarray, centres: np.ndarray, shape: tuple[int, int]) -> tuple[float, float]:
    """How far an affine field fitted to the tile offsets moves between the image's centre and its corners.

    A rotation or scale error left by a registration grows towards the corners; a translation moves all alike and
    counts zero. Returns the largest deviation (pixels, over corners and axes) and its standard error. Tiles farther
    than 3 scaled deviations from a first fit are left out of the second.
    """
    design = np.hstack([np.ones((len(centres), 1)), centres / np.array(shape) - 0.5])
    keep = np.ones(len(shifts), dtype=bool)
    for _ in range(2):
        coefficients, *_ = np.linalg.lstsq(design[keep], shifts[keep], rcond=None)
        residual = np.abs(shifts - design @ coefficients)
        scale = 1.4826 * np.median(residual[keep], axis=0) + 0.05
        if (residual <= 3 * scale).all(axis=1).sum() < 6:
            break
        keep = (residual <= 3 * scale).all(axis=1)
    noise = np.sqrt((residual[keep] ** 2).sum(axis=0) / max(keep.sum() - 3, 1))  # per axis
    covariance = np.linalg.pinv(design[keep].T @ design[keep])[1:, 1:]
    corners = np.array([[row, col] for row in (-0.5, 0.5) for col in (-0.5, 0.5)])
    deviations = np.abs(corners @ coefficients[1:])  # (4 corners, 2 axes)
    errors = np.sqrt(np.einsum("ci,ij,cj->c", corners, covariance, corners))[:, None] * noise
    worst = np.unravel_index(np.argmax(deviations), deviations.shape)
    return float(deviations[worst]), float(errors[worst])


def verdict(measured: dict, tolerance: float) -> tuple[bool, np.ndarray | None]:
    """(aligned, consistent offset or None): the whole-image peak and the tiles' median must agree within tolerance."""
    whole = np.array(measured["whole_image_offset_dy_dx"])
    if measured["whole_image_peak_on_edge"] or measured["tiles_agreeing"] < 3:
        return False, None
    tiles = np.array(measured["tiles_median_offset_dy_dx"])
    if np.abs(whole - tiles).max() > tolerance:
        return False, None
    # a rotation or scale error that is both real (2 standard errors) and large: no shift can fix it
    corner = measured.get("tiles_affine_corner_deviation", 0.0) - 2 * measured.get(
        "tiles_affine_corner_deviation_error", 0.0
    )
    if corner > 2 * tolerance:
        return False, None
    return bool(np.abs(whole).max() <= tolerance and np.abs(tiles).max() <= tolerance), (whole + tiles) / 2


def shift_crop(pair: Pair, offset: np.ndarray) -> None:
    """Crop both images so that the captured content moved by ``offset`` (whole pixels) lines up; no resampling."""
    dy, dx = (int(v) for v in np.round(offset))
    height, width = pair.reference.shape
    ref_rows = slice(max(0, -dy), height - max(0, dy))
    ref_cols = slice(max(0, -dx), width - max(0, dx))
    cap_rows = slice(max(0, dy), height - max(0, -dy))
    cap_cols = slice(max(0, dx), width - max(0, -dx))
    pair.reference = pair.reference[ref_rows, ref_cols]
    pair.captured = pair.captured[cap_rows, cap_cols]
    if pair.changed is not None:
        pair.changed = pair.changed[ref_rows, ref_cols] | pair.changed[cap_rows, cap_cols]
    pair.notes.append(f"captured moved by ({dy}, {dx}) px (rows, cols) to cancel a measured offset; both cropped")


def largest_rectangle(mask: np.ndarray) -> tuple[slice, slice]:
    """The largest axis-aligned all-True rectangle of a boolean mask (histogram method)."""
    heights = np.zeros(mask.shape[1], dtype=int)
    best = (0, slice(0, 0), slice(0, 0))
    for row, line in enumerate(mask):
        heights = np.where(line, heights + 1, 0)
        stack: list[int] = []
        for col in range(len(heights) + 1):
            height = heights[col] if col < len(heights) else 0
            while stack and heights[stack[-1]] >= height:
                top = stack.pop()
                left = stack[-1] + 1 if stack else 0
                area = heights[top] * (col - left)
                if area > best[0]:
                    best = (area, slice(row - heights[top] + 1, row + 1), slice(left, col))
            stack.append(col)
    return best[1], best[2]


def content_mask(image: np.ndarray) -> np.ndarray:
    """False where a rotated source left black fill: near-black regions touching the border, widened 2 px."""
    dark, _ = ndimage.label(image < 4)
    border = np.unique(np.concatenate([dark[0], dark[-1], dark[:, 0], dark[:, -1]]))
    fill = np.isin(dark, border[border > 0])
    return ~ndimage.binary_dilation(fill, iterations=2)


def warp(source: np.ndarray, matrix: np.ndarray, shape: tuple[int, int], scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``out[y, x] = source(matrix @ (x, y, 1))`` (0-based pixels), cubic, low-passed when ``scale`` > 1 shrinks.

    Returns the warped image and where it is covered by the source's content.
    """
    if scale > 1.0:  # the output pixel spans `scale` source pixels: anti-alias first
        source = ndimage.gaussian_filter(source, 0.5 * np.sqrt(scale**2 - 1.0))
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    points = matrix @ np.stack([cols.ravel(), rows.ravel(), np.ones(rows.size)])
    x, y = points[0] / points[2], points[1] / points[2]
    out = ndimage.map_coordinates(source, [y, x], order=3, mode="nearest").reshape(shape)
    inside = ndimage.map_coordinates(content_mask(source).astype(float), [y, x], order=0, cval=0.0).reshape(shape)
    return out, inside > 0.5


def coregister(
    first: np.ndarray, second: np.ndarray, first_to_second: np.ndarray
) -> tuple[np.ndarray, np.ndarray, str]:
    """Resample one image into the other's frame: the one keeping more common ground, the coarser one on a tie."""
    linear_scale = float(np.sqrt(abs(np.linalg.det(first_to_second[:2, :2]))))  # second pixels per first pixel
    options = []
    warped, covered = warp(second, first_to_second, first.shape, linear_scale)
    rows, cols = largest_rectangle(covered & content_mask(first))
    ground = (rows.stop - rows.start) * (cols.stop - cols.start) * linear_scale**2  # in second-image pixels
    options.append((round(ground, -2), linear_scale > 1, first[rows, cols], warped[rows, cols], "first"))
    warped, covered = warp(first, np.linalg.inv(first_to_second), second.shape, 1.0 / linear_scale)
    rows, cols = largest_rectangle(covered & content_mask(second))
    ground = (rows.stop - rows.start) * (cols.stop - cols.start)
    options.append((round(ground, -2), linear_scale < 1, warped[rows, cols], second[rows, cols], "second"))
    *_, first_out, second_out, frame = max(options, key=lambda option: option[:2])
    return first_out, second_out, f"resampled into the {frame} image's frame (scale {linear_scale:.3f})"


def matlab_to_zero_based(matrix: np.ndarray) -> np.ndarray:
    """A 3x3 map between 1-based (x, y) pixel coordinates, rewritten for 0-based ones."""
    one = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    return np.linalg.inv(one) @ matrix @ one


CHANGE_FOLDERS = (("A", "B"), ("prev", "curr"))  # (earlier date, later date) folder names, as published


def read_change_folders(source: Path, dataset: str) -> Iterator[Pair]:
    """LEVIR-CD / DSIFN-CD / WHU-CD layout: A/, B/ (or prev/, curr/) and label/ with same-named images."""
    earlier, later = next(
        (names for names in CHANGE_FOLDERS if (source / names[0]).is_dir()),
        CHANGE_FOLDERS[0],
    )
    for path in sorted((source / earlier).iterdir()):
        other = source / later / path.name
        if not other.exists():
            continue
        reference, captured = read_grey(path), read_grey(other)
        if reference.shape != captured.shape:
            continue
        label = source / "label" / path.name
        changed = read_grey(label) > 127 if label.exists() else None
        yield Pair(path.stem, reference, captured, {"paths": [str(p) for p in (path, other)]}, changed)


def read_oscd(source: Path, dataset: str) -> Iterator[Pair]:
    """OSCD: Sentinel-2 B04/B03/B02 of each city's two dates."""
    import tifffile

    for city in sorted(p for p in source.iterdir() if (p / "imgs_1").is_dir()):
        greys = []
        for folder in ("imgs_1", "imgs_2"):
            bands = [next((city / folder).glob(f"*_{band}.tif")) for band in ("B04", "B03", "B02")]
            greys.append(stretch(np.stack([tifffile.imread(b).astype(np.float64) for b in bands], -1) @ LUMA))
        rows, cols = min(g.shape[0] for g in greys), min(g.shape[1] for g in greys)
        notes = (
            [f"dates differ in size {[g.shape for g in greys]}: cropped to {rows} x {cols}"]
            if greys[0].shape != greys[1].shape
            else []
        )
        greys = [g[:rows, :cols] for g in greys]
        labels = [
            city / "cm" / "cm.png",
            source.parent / f"{source.name.replace('Images', 'Train Labels')}" / city.name / "cm" / "cm.png",
        ]
        label = next((path for path in labels if path.exists()), None)
        changed = read_grey(label)[:rows, :cols] > 127 if label is not None else None
        dates = (city / "dates.txt").read_text().split() if (city / "dates.txt").exists() else []
        yield Pair(city.name, greys[0], greys[1], {"paths": [str(city)], "dates": dates[1::2]}, changed, notes)


def read_pix2pix_maps(source: Path, dataset: str) -> Iterator[Pair]:
    """pix2pix maps: side-by-side jpgs (photograph left, map right), or a test run's ``N_real_A/B.png`` images.

    In a test run's output the direction (AtoB or BtoA) decides which of A and B is the map: the one with the weaker
    mean gradient (flat colours) is taken as the map.
    """
    for path in sorted(source.rglob("*_real_A.png"), key=lambda p: int(p.stem.split("_")[0])):
        first, second = read_grey(path), read_grey(path.with_name(path.name.replace("_real_A", "_real_B")))
        if gradient_magnitude(first).mean() > gradient_magnitude(second).mean():
            first, second = second, first
        paths = [str(path), str(path.with_name(path.name.replace("_real_A", "_real_B")))]
        yield Pair(path.stem.split("_")[0], first, second, {"paths": paths})
    for path in sorted(source.rglob("*.jpg"), key=lambda p: (p.parent.name, int(p.stem) if p.stem.isdigit() else 0)):
        image = read_grey(path)
        height, width = image.shape
        if width != 2 * height:  # resized or cropped copies whose halves are not square cannot be split exactly
            continue
        yield Pair(f"{path.parent.name}{path.stem}", image[:, height:], image[:, :height], {"paths": [str(path)]})


def read_srif(source: Path, dataset: str) -> Iterator[Pair]:
    """SRIF: pairN_1 / pairN_2 with the similarity gt_N (1-based pixels of the first into the second)."""
    folder = (
        source
        / {
            "optical-map": "Optical-Map",
            "optical-sar": "Optical-SAR",
            "optical-infrared": "Optical-Infrared",
            "optical-optical": "Optical-Optical",
        }[dataset.removeprefix("srif-")]
    )
    numbers = sorted(int(p.stem.split("_")[1]) for p in folder.glob("gt_*.txt"))
    for number in numbers:
        paths = [folder / f"pair{number}_{side}.jpg" for side in (1, 2)]
        first, second = read_grey(paths[0]), read_grey(paths[1])
        matrix = matlab_to_zero_based(np.vstack([np.loadtxt(folder / f"gt_{number}.txt"), [0.0, 0.0, 1.0]]))
        if np.allclose(matrix, np.eye(3)) and first.shape == second.shape:
            how = "given as co-registered (identity ground truth)"
        else:
            first, second, how = coregister(first, second, matrix)
        meta = {"paths": [str(p) for p in paths], "registration": how}
        if dataset == "srif-optical-map":  # the map rendering is the map in the yardstick's roles
            yield Pair(f"{number:03d}", second, first, meta | {"roles": "reference = pair_2 (map), captured = pair_1"})
        else:
            yield Pair(f"{number:03d}", first, second, meta)


CFOG_PAIRS = (  # reference image, sensed image, control points (reference x y, sensed x y), modality of each
    ("data/optical_ref.png", "data/SAR_sen.png", "data/OpticaltoSAR_CP.txt", "optical", "SAR"),
    ("data/LidarDepth_ref.png", "data/optical1_sen.png", "data/LidartoOptical_CP.txt", "lidar depth", "optical"),
    ("data/visible_ref.tif", "data/infrared_sen.tif", "data/VisibletoInfrared_CP.txt", "optical", "infrared"),
    ("data/Stest3_ref.tif", "data/Stest3_sen.tif", "data/Stest3gcp.pts", "optical", "SAR"),
    (
        "other data/optical-LiDAR/LiDARintensity1_sen.tif",
        "other data/optical-LiDAR/visible1_ref.tif",
        "other data/optical-LiDAR/LiDARToVisible1.txt",
        "lidar intensity",
        "optical",
    ),
    (
        "other data/optical-LiDAR/LiDARintensity2_sen.png",
        "other data/optical-LiDAR/visible2_ref.png",
        "other data/optical-LiDAR/LiDARToVisible2.txt",
        "lidar intensity",
        "optical",
    ),
    (
        "other data/optical-Map/optical1_ref.tif",
        "other data/optical-Map/map1_sen.tif",
        "other data/optical-Map/opticalToMap1_CP.txt",
        "optical",
        "map",
    ),
    (
        "other data/optical-Map/optical2_ref.tif",
        "other data/optical-Map/map2_sen.tif",
        "other data/optical-Map/opticalToMap2_CP.txt",
        "optical",
        "map",
    ),
    (
        "other data/visible-SAR/visible1_ref.tif",
        "other data/visible-SAR/SAR1_sen.tif",
        "other data/visible-SAR/visibleToSAR1_CP.txt",
        "optical",
        "SAR",
    ),
    (
        "other data/visible-infrared/test6_ref.tif",
        "other data/visible-infrared/test6_sen.tif",
        "other data/visible-infrared/VisibletoInfrared_CP.txt",
        "optical",
        "infrared",
    ),
)


def read_cfog(source: Path, dataset: str) -> Iterator[Pair]:
    """CFOG: each sensed image resampled into its reference's frame by the affine fitted to the control points."""
    for reference_path, sensed_path, points_path, reference_kind, sensed_kind in CFOG_PAIRS:
        paths = [source / reference_path, source / sensed_path, source / points_path]
        if not all(p.exists() for p in paths):
            continue
        reference, sensed = read_grey(paths[0]), read_grey(paths[1])
        points = np.loadtxt(paths[2])[:, :4] - 1.0  # MATLAB's 1-based pixels
        design = np.hstack([points[:, :2], np.ones((len(points), 1))])
        affine, *_ = np.linalg.lstsq(design, points[:, 2:4], rcond=None)
        residual = points[:, 2:4] - design @ affine
        matrix = np.vstack([affine.T, [0.0, 0.0, 1.0]])
        warped, covered = warp(sensed, matrix, reference.shape, 1.0)
        rows, cols = largest_rectangle(covered & content_mask(reference))
        reference, warped = reference[rows, cols], warped[rows, cols]
        # the yardstick's map: the street map where there is one, else the optical image
        swap = sensed_kind == "map" or (reference_kind != "optical" and reference_kind != "map")
        meta = {
            "paths": [str(p) for p in paths],
            "modalities": [sensed_kind, reference_kind] if swap else [reference_kind, sensed_kind],
            "registration": f"affine least squares on {len(points)} control points (rms residual "
            f"{np.sqrt((residual**2).sum(1).mean()):.2f} px), sensed image resampled (cubic) into the reference frame",
        }
        name = Path(sensed_path).stem.removesuffix("_sen").removesuffix("_ref")
        yield Pair(name, warped if swap else reference, reference if swap else warped, meta)


DATASETS = {  # name: (reader, case, licence as the source states it)
    "levir-cd": (
        read_change_folders,
        "date",
        "LEVIR-CD: Google Earth imagery; no licence in the copies read (cite Chen & Shi 2020)",
    ),
    "dsifn-cd": (read_change_folders, "date", "DSIFN-CD: Google Earth imagery; no licence stated by the source"),
    "whu-cd": (read_change_folders, "date", "WHU-CD: aerial photographs (Ji et al. 2019); no licence in the copy read"),
    "oscd": (read_oscd, "date", "modified Copernicus Sentinel data 2015-2018 (free and open); change maps CC BY-NC-SA"),
    "pix2pix-maps": (read_pix2pix_maps, "modality", "pix2pix maps (Google Maps); no licence stated, Google's terms"),
    "srif-optical-map": (read_srif, "modality", "SRIF dataset (Li et al. 2023): no licence stated; cite the paper"),
    "srif-optical-sar": (read_srif, "modality", "SRIF dataset (Li et al. 2023): no licence stated; cite the paper"),
    "srif-optical-infrared": (
        read_srif,
        "modality",
        "SRIF dataset (Li et al. 2023): no licence stated; cite the paper",
    ),
    "srif-optical-optical": (read_srif, "date", "SRIF dataset (Li et al. 2023): no licence stated; cite the paper"),
    "cfog": (read_cfog, "modality", "CFOG (Ye et al. 2019): research purposes only, no commercial use"),
}


def write_manifest(out: Path, rejected: list[dict]) -> None:
    """List every pair folder under ``out`` (with its shape and measured offset) and this run's rejections."""
    pairs = []
    for meta_path in sorted(out.glob("*/*/meta.json")):
        meta = json.loads(meta_path.read_text())
        pairs.append(
            {key: meta[key] for key in ("case", "dataset", "id", "shape", "licence")}
            | {
                "folder": str(meta_path.parent.relative_to(out)),
                "offset_dy_dx": meta["alignment"]["whole_image_offset_dy_dx"],
            }
        )
    previous = (
        json.loads((out / "manifest.json").read_text()).get("rejected", []) if (out / "manifest.json").exists() else []
    )
    names = {(r["dataset"], r["id"]) for r in rejected}
    rejected = [r for r in previous if (r["dataset"], r["id"]) not in names] + rejected
    kept = {(p["dataset"], p["id"]) for p in pairs}
    rejected = [r for r in rejected if (r["dataset"], r["id"]) not in kept]
    (out / "manifest.json").write_text(json.dumps({"pairs": pairs, "rejected": rejected}, indent=1) + "\n")


def tiles_of(pairs: Iterator[Pair], size: int | None) -> Iterator[Pair]:
    """Each pair cut into non-overlapping ``size`` x ``size`` tiles named ``<id>_<row>_<col>`` (None: as it is)."""
    for pair in pairs:
        if size is None:
            yield pair
            continue
        height, width = pair.reference.shape
        for top in range(0, height - size + 1, size):
            for left in range(0, width - size + 1, size):
                box = (slice(top, top + size), slice(left, left + size))
                yield Pair(
                    f"{pair.name}_{top:04d}_{left:04d}",
                    pair.reference[box],
                    pair.captured[box],
                    pair.meta | {"tile_top_left": [top, left]},
                    None if pair.changed is None else pair.changed[box],
                    list(pair.notes),
                )


def prepare(
    dataset: str,
    source: Path,
    out: Path,
    limit: int | None,
    tolerance: float,
    correct: bool,
    origin: str | None = None,
    tile: int | None = None,
) -> tuple[int, int]:
    """Read, check, write; returns (kept, rejected)."""
    reader, case, licence = DATASETS[dataset]
    out.mkdir(parents=True, exist_ok=True)
    kept, rejected = 0, []
    for pair in tiles_of(reader(source, dataset), tile):
        if limit is not None and kept >= limit:
            break
        if min(pair.reference.shape) < MIN_SIDE:
            rejected.append({"dataset": dataset, "id": pair.name, "reason": f"smaller than {MIN_SIDE} px"})
            continue
        score = "nmi" if case == "modality" else "gradient-ncc"
        measured = measure_offset(pair.reference, pair.captured, pair.changed, score)
        aligned, offset = verdict(measured, tolerance)
        before = None
        if not aligned and correct and offset is not None:
            before = measured
            shift_crop(pair, offset)
            measured = measure_offset(pair.reference, pair.captured, pair.changed, score)
            aligned, _ = verdict(measured, tolerance)
        if not aligned:
            rejected.append({"dataset": dataset, "id": pair.name, "reason": "alignment not verified", **measured})
            print(f"  {dataset}-{pair.name}: rejected {measured['whole_image_offset_dy_dx']}", file=sys.stderr)
            continue
        folder = out / CASES[case] / f"{dataset}-{pair.name}"
        folder.mkdir(parents=True, exist_ok=True)
        np.save(folder / "reference.npy", pair.reference.astype(np.float32))
        np.save(folder / "captured.npy", pair.captured.astype(np.float32))
        if pair.changed is not None:
            np.save(folder / "changed.npy", pair.changed)
        pair.meta["paths"] = [str(Path(path).relative_to(source)) for path in pair.meta["paths"]]
        meta = {
            "case": CASES[case],
            "dataset": dataset,
            "id": pair.name,
            "shape": list(pair.reference.shape),
            "licence": licence,
            "origin": origin,
            **pair.meta,
            "notes": pair.notes,
            "alignment": measured,
        }
        if before is not None:
            meta["alignment_before_correction"] = before
        (folder / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
        kept += 1
        print(f"  {folder.name}: {pair.reference.shape}, offset {measured['whole_image_offset_dy_dx']}")
    write_manifest(out, rejected)
    return kept, len(rejected)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("--dataset", required=True, choices=sorted(DATASETS))
    parser.add_argument("--source", required=True, type=Path, help="the downloaded dataset folder (see below)")
    parser.add_argument("--out", required=True, type=Path, help="where the case folders and manifest.json go")
    parser.add_argument("--limit", type=int, default=None, help="keep at most this many pairs")
    parser.add_argument("--tolerance", type=float, default=0.5, help="largest residual offset kept, pixels (0.5)")
    parser.add_argument("--correct", action="store_true", help="cancel a consistent measured offset by cropping")
    parser.add_argument("--origin", default=None, help="where the copy came from (repository@commit), kept in meta")
    parser.add_argument("--tile", type=int, default=None, help="cut each pair into N x N tiles, each checked alone")
    args = parser.parse_args(argv)
    if not args.source.is_dir():
        parser.error(f"--source: expected a folder, got {args.source}")
    if args.limit is not None and args.limit < 1:
        parser.error(f"--limit: expected a positive count, got {args.limit}")
    if args.tolerance <= 0:
        parser.error(f"--tolerance: expected a positive number of pixels, got {args.tolerance}")
    if args.tile is not None and args.tile < MIN_SIDE:
        parser.error(f"--tile: expected at least {MIN_SIDE} pixels, got {args.tile}")
    try:
        kept, rejected = prepare(
            args.dataset, args.source, args.out, args.limit, args.tolerance, args.correct, args.origin, args.tile
        )
    except (OSError, ValueError, StopIteration, KeyError) as error:
        parser.error(f"--source: {args.source} does not hold the {args.dataset} layout ({error!r})")
    if kept == 0:
        parser.error(f"--source: no {args.dataset} pair found or verified under {args.source} ({rejected} rejected)")
    print(f"{args.dataset}: {kept} pairs kept, {rejected} rejected; manifest {args.out / 'manifest.json'}")


if __name__ == "__main__":
    main()
