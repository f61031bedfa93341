"""Input checks shared by every public function: each message names the argument, what was expected and what came.

Checks on tensor *values* (finiteness, positivity, empty masks) need the values on the host. They run for CPU
tensors; on accelerators they are off by default so that the forward pass never synchronises, and can be turned on
with :func:`value_checks` (or ``ENMI_TORCH_VALUE_CHECKS=1``) while debugging.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Iterator, Sequence
from typing import Any

import torch
from torch import Tensor

# None: on for CPU tensors, off on accelerators (no stream synchronisation); True or False: on or off everywhere.
_VALUE_CHECKS: bool | None = {"1": True, "0": False}.get(os.environ.get("ENMI_TORCH_VALUE_CHECKS", ""))
MAX_BINS = 1 << 24


@contextlib.contextmanager
def value_checks(enabled: bool | None = True) -> Iterator[None]:
    """Turn the value checks (NaN/inf pixels, non-positive variance, empty masks, unresolved bins) on or off.

    By default (``None``) they run on CPU tensors and are off on accelerators, where reading values on the host
    synchronises the stream. ``True`` runs them everywhere (while debugging on a GPU), ``False`` nowhere (they cost
    about 10 % of a small loss's forward pass on CPU). ``ENMI_TORCH_VALUE_CHECKS=1`` or ``=0`` sets the default.
    Shape, type and option checks always run.

    Example:
        >>> import torch
        >>> from enmi_torch.functional import nmi
        >>> from enmi_torch.utils.checks import value_checks
        >>> with value_checks(False):
        ...     nmi(torch.rand(1, 1, 8, 8), torch.rand(1, 1, 8, 8)).shape
        torch.Size([1])
    """
    global _VALUE_CHECKS
    if enabled is not None and not isinstance(enabled, bool):
        raise TypeError(f"enabled must be True, False or None, got {enabled!r}")
    previous = _VALUE_CHECKS
    _VALUE_CHECKS = enabled
    try:
        yield
    finally:
        _VALUE_CHECKS = previous


def _values_checked(tensor: Tensor) -> bool:
    if torch.compiler.is_compiling():
        return False
    if _VALUE_CHECKS is None:
        return tensor.device.type == "cpu"
    return _VALUE_CHECKS


def check_tensor(name: str, value: Any) -> Tensor:
    """Raise ``TypeError`` unless ``value`` is a tensor."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    return value


def check_bool_mask(name: str, value: Any) -> Tensor:
    """Raise ``TypeError`` unless ``value`` is a bool tensor (a mask); return it."""
    check_tensor(name, value)
    if value.dtype != torch.bool:
        raise TypeError(f"{name} must be a bool tensor, got dtype {value.dtype}")
    return value


def check_variance_given(variance: Any) -> None:
    """Raise ``ValueError`` if a score that weighs pixels by their noise got no ``variance``."""
    if variance is None:
        raise ValueError("variance must be a number or a tensor of per-pixel variances, got None")


def check_floating(name: str, value: Any) -> Tensor:
    """Raise ``TypeError`` unless ``value`` is a floating-point tensor."""
    check_tensor(name, value)
    if not value.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got dtype {value.dtype}")
    return value


def check_option(name: str, value: Any, allowed: Sequence[str]) -> str:
    """Raise ``ValueError`` unless ``value`` is one of the ``allowed`` strings."""
    if not isinstance(value, str) or value not in allowed:
        raise ValueError(f"{name} must be one of {list(allowed)}, got {value!r}")
    return value


def check_bool(name: str, value: Any) -> bool:
    """Raise ``TypeError`` unless ``value`` is ``True`` or ``False`` (a truthy ``'no'`` must not switch a step on)."""
    if not isinstance(value, bool):
        raise TypeError(f"{name} must be a bool (True or False), got {type(value).__name__} {value!r}")
    return value


def check_bins(bins: Any, name: str = "bins") -> int:
    """Raise unless ``bins`` is an integer in ``[2, 2**24]``; ``name``: the argument as the caller's user gives it."""
    if isinstance(bins, bool) or not isinstance(bins, int):
        raise TypeError(f"{name} must be an int >= 2, got {type(bins).__name__} {bins!r}")
    if bins < 2:
        raise ValueError(f"{name} must be an int >= 2, got {bins}")
    if bins > MAX_BINS:
        # Beyond 2**24 float32 values no longer tell neighbouring bins apart (and bins**2 cell indices near int64's).
        raise ValueError(f"{name} must be at most {MAX_BINS} (2**24), got {bins}")
    return bins


def check_value_range(value_range: Any, name: str = "value_range") -> tuple[float, float]:
    """Raise ``ValueError`` unless ``value_range`` is two finite numbers ``(low, high)`` with ``low < high``."""
    try:
        low, high = (float(bound) for bound in value_range)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair of finite numbers (low, high), got {value_range!r}") from None
    if not (math.isfinite(low) and math.isfinite(high)) or low >= high:
        raise ValueError(f"{name} must be finite with low < high, got {value_range!r}")
    if not math.isfinite(high - low):
        # Bin widths and positions are taken from high - low: it must be a float64 number too.
        raise ValueError(f"{name} must have a finite width high - low (at most ~1.8e308), got {value_range!r}")
    return low, high


def check_margin(
    name: str, value: Any, *, positive: bool = False, meaning: str = "cells from the map's border"
) -> float:
    """Raise unless ``value`` is a finite number ``>= 0`` (``> 0`` with ``positive``); ``meaning`` in the message.

    A negative margin would count samples off the map (zero padding) as observed; NaN would drop every sample.
    """
    expected = f"a finite number {'> 0' if positive else '>= 0'} ({meaning})"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{name} must be {expected}, got {type(value).__name__} {value!r}")
    if not math.isfinite(value) or value < 0 or (positive and value == 0):
        raise ValueError(f"{name} must be {expected}, got {value!r}")
    return float(value)


def check_positive_number(name: str, value: Any) -> float:
    """Raise ``ValueError`` unless ``value`` is a finite number greater than zero."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{name} must be a positive number, got {type(value).__name__} {value!r}")
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


def check_positive_int(name: str, value: Any) -> int:
    """Raise unless ``value`` is an integer >= 1 (``bool`` is refused)."""
    return _check_int_at_least(name, value, 1)


def check_non_negative_int(name: str, value: Any) -> int:
    """Raise unless ``value`` is an integer >= 0 (``bool`` is refused)."""
    return _check_int_at_least(name, value, 0)


def _check_int_at_least(name: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name} must be an int >= {low}, got {type(value).__name__} {value!r}")
    if value < low:
        raise ValueError(f"{name} must be an int >= {low}, got {value}")
    return value


def check_shifts(shifts: Any) -> tuple[int, int]:
    """Raise unless ``shifts`` is a search radius ``r >= 0`` or a pair ``(ry, rx)`` of them; returns the pair."""
    pair = (shifts, shifts) if isinstance(shifts, int) and not isinstance(shifts, bool) else shifts
    if (
        not isinstance(pair, (tuple, list))
        or len(pair) != 2
        or not all(isinstance(value, int) and not isinstance(value, bool) and value >= 0 for value in pair)
    ):
        raise ValueError(f"shifts must be an int >= 0 or a pair (ry, rx) of them, got {shifts!r}")
    return int(pair[0]), int(pair[1])


def check_not_empty(name: str, images: Tensor) -> None:
    """Raise ``ValueError`` unless the batch ``images`` ``(B, ...)`` holds at least one sample and one pixel."""
    if images.numel() == 0:
        raise ValueError(f"{name} must hold at least one sample and one pixel, got shape {tuple(images.shape)}")


def check_image_shape(name: str, value: Any) -> tuple[int, int]:
    """Raise unless ``value`` is a pair of positive integers ``(H, W)``; returns it as a tuple.

    ``torch.Size`` and integer tensors' sizes count; ``4.5`` is refused, not rounded.
    """
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 2:
        raise ValueError(f"{name} must be (H, W), two positive ints, got {value!r}")
    if any(isinstance(size, bool) or not isinstance(size, int) or size < 1 for size in value):
        raise ValueError(f"{name} must be (H, W), two positive ints, got {value!r}")
    return int(value[0]), int(value[1])


def check_pose(name: str, pose: Any, batch: int | None = None) -> Tensor:
    """Raise unless ``pose`` is a floating ``(B, 3)`` tensor ``(x, y, yaw)`` (``batch`` rows if given), finite.

    Returns it unchanged (the caller picks the compute dtype). Meta and complex tensors are refused by name; the
    finiteness check reads the values on the host (a pose is small).
    """
    check_floating(name, pose)
    check_real_data(name, pose)
    expected = "(B, 3)" if batch is None else f"({batch}, 3)"
    if pose.ndim != 2 or pose.shape[1] != 3 or (batch is not None and pose.shape[0] != batch):
        raise ValueError(f"{name} must have shape {expected}, rows (x, y, yaw), got {tuple(pose.shape)}")
    if pose.shape[0] == 0:
        raise ValueError(f"{name} must hold at least one row (x, y, yaw), got shape {tuple(pose.shape)}")
    if not bool(torch.isfinite(pose).all()):
        raise ValueError(f"{name} must be finite, got NaN or inf in {pose.tolist()}")
    return pose


def check_map(name: str, value: Any, batch: int, like_name: str, like: Tensor) -> Tensor:
    """Raise unless ``value`` is a real floating map ``(1 or batch, 1, Hm, Wm)`` on the device of ``like``."""
    check_floating(name, value)
    check_real_data(name, value)
    if value.ndim != 4 or value.shape[1] != 1 or value.shape[0] not in (1, batch) or value.numel() == 0:
        shapes = "(1, 1, Hm, Wm)" + ("" if batch == 1 else f" or ({batch}, 1, Hm, Wm)")
        raise ValueError(
            f"{name} must have shape {shapes} with Hm, Wm >= 1 for {like_name} of batch {batch}, got "
            f"{tuple(value.shape)}"
        )
    check_same_device(name, value, like_name, like)
    return value


def check_mask_of(name: str, mask: Any, like_name: str, like: Tensor) -> Tensor:
    """Raise unless ``mask`` is a bool ``(1 or B, 1, H, W)`` (or ``(H, W)``) mask of the ``(B, 1, H, W)`` ``like``.

    A mask of another size than what it masks would leave cells beyond it counted as observed (or fail in
    ``expand``). Returns it as ``(1 or B, 1, H, W)`` on ``like``'s device.
    """
    check_bool_mask(name, mask)
    check_real_data(name, mask)
    spatial = tuple(like.shape[-2:])
    if mask.ndim == 2:
        mask = mask[None, None]
    if mask.ndim != 4 or tuple(mask.shape[1:]) != (1, *spatial) or mask.shape[0] not in (1, like.shape[0]):
        batch = like.shape[0]
        shapes = f"(1, 1, {spatial[0]}, {spatial[1]})" + (
            "" if batch == 1 else f" or ({batch}, 1, {spatial[0]}, {spatial[1]})"
        )
        raise ValueError(
            f"{name} must be as large as {like_name}, {shapes} or {spatial}, got {tuple(mask.shape)} for {like_name} "
            f"of shape {tuple(like.shape)}"
        )
    check_same_device(name, mask, like_name, like)
    return mask


FAR_OUTSIDE = 8  # range widths beyond value_range past which a pixel counts as far outside it


def check_resolved_by_bins(
    name: str, values: Tensor, valid: Tensor | None, bins: int, value_range: tuple[float, float]
) -> None:
    """Raise if a sample of ``values`` ``(B, N)`` varies but all its valid values fall in one bin (a value check).

    That is the signature of a wrong ``value_range`` (images in ``[0, 1]`` against the default ``(0, 256)``): the
    histogram would hold one captured bin, the score would be that of independent images and its gradient 0.
    """
    if not _values_checked(values):
        return
    low, high = value_range
    index = ((values - low) * (bins / (high - low))).floor().clamp(0, bins - 1)
    keep = torch.ones_like(values, dtype=torch.bool) if valid is None else valid.expand_as(values)
    large = torch.finfo(values.dtype).max
    smallest = torch.where(keep, values, large).amin(-1)
    largest = torch.where(keep, values, -large).amax(-1)
    one_bin = torch.where(keep, index, bins).amin(-1) == torch.where(keep, index, -1).amax(-1)
    unresolved = one_bin & (largest > smallest)
    if bool(unresolved.any()):
        sample = int(unresolved.nonzero()[0, 0])
        raise ValueError(
            f"{name} varies ({float(smallest[sample]):.4g} to {float(largest[sample]):.4g} in sample {sample}) but all "
            f"its valid pixels fall in one of the {bins} bins of value_range={value_range}, so the score could not see "
            f"it; pass a value_range that covers the values (e.g. value_range=(0.0, 1.0) for images in [0, 1])"
        )
    # Most valid pixels far outside the range (0-255 images against value_range=(0, 1)): they all clip into the edge
    # bins and the few inside decide the score. Noise spilling past the range's edges stays well under this: the
    # paper's simulation at its largest noise power (std up to 2.5 range widths) puts under a tenth of the pixels there.
    width = FAR_OUTSIDE * (high - low)
    far = ((values < low - width) | (values > high + width)) & keep
    far_share = far.sum(-1) / keep.sum(-1).clamp_min(1)
    if bool((far_share > 0.5).any()):
        sample = int((far_share > 0.5).nonzero()[0, 0])
        raise ValueError(
            f"{name} lies far outside value_range={value_range}: {float(far_share[sample]):.0%} of its valid pixels "
            f"in sample {sample} are more than {FAR_OUTSIDE} range widths beyond it ({float(smallest[sample]):.4g} to "
            f"{float(largest[sample]):.4g}), so they would all clip into the edge bins; pass a value_range that "
            f"covers the values (e.g. value_range=(0.0, 256.0) for 8-bit images)"
        )


def check_finite_where(name: str, values: Tensor, valid: Tensor | None, mask_name: str = "valid_mask") -> None:
    """Raise ``ValueError`` if ``values`` holds NaN or inf at a valid position (a value check).

    ``mask_name``: the argument the caller's user gives ``valid`` as, named in the message.
    """
    if not _values_checked(values):
        return
    bad = ~torch.isfinite(values)
    if valid is not None:
        bad = bad & valid
    if bool(bad.any()):
        count = int(bad.sum())
        raise ValueError(
            f"{name} must be finite where {mask_name} is True, got {count} NaN/inf value(s); "
            f"mask them out with {mask_name}"
        )


def fitted_to(name: str, values: Tensor, dtype: torch.dtype, remedy: str) -> Tensor:
    """``values`` cast to ``dtype``; raise ``ValueError`` if a finite value overflows there (a value check).

    A result computed in a wider dtype than it is returned in must not turn into inf silently on the way out.
    """
    result = values.to(dtype)
    if not _values_checked(values) or values.dtype == dtype:
        return result
    lost = torch.isfinite(values) & ~torch.isfinite(result)
    if bool(lost.any()):
        largest = float(values[lost].abs().max())
        raise ValueError(
            f"{name} reaches {largest:.3g}, beyond the largest {dtype} ({torch.finfo(dtype).max:.3g}): {remedy}"
        )
    return result


FLOAT32_MAGNITUDE = 1e18  # float32 sums of squares of larger values overflow (its largest value is 3.4e38)


def check_magnitude(name: str, values: Tensor, valid: Tensor | None, mask_name: str = "valid_mask") -> None:
    """Raise ``ValueError`` if float32 ``values`` exceed :data:`FLOAT32_MAGNITUDE` at a valid position (a value check).

    The scores form squares and products of the values; in float32 those overflow into inf or NaN past ~1e19.
    """
    if values.dtype != torch.float32 or not _values_checked(values):
        return
    large = values.abs() > FLOAT32_MAGNITUDE
    if valid is not None:
        large = large & valid.expand_as(large)
    if bool(large.any()):
        raise ValueError(
            f"{name} holds {int(large.sum())} value(s) beyond +-{FLOAT32_MAGNITUDE:.0e} where {mask_name} is True "
            f"(largest {float(values[large].abs().max()):.3g}); float32 sums of their squares would overflow: pass "
            f"float64 images (.double()), rescale them, or mask those pixels out"
        )


def check_variance_fits(name: str, variance: Tensor | float, dtype: torch.dtype, valid: Tensor | None = None) -> None:
    """Raise ``ValueError`` if a positive finite variance underflows or overflows ``dtype`` (a value check).

    ``variance``: a number, or a tensor broadcast like ``valid`` (``None``: every entry counts). A variance of 1e-40 is
    0 or subnormal in float32 (NaN weights) and one of 1e39 is inf there.
    """
    info = torch.finfo(dtype)
    if isinstance(variance, Tensor):
        if not _values_checked(variance) or torch.finfo(variance.dtype).max <= info.max / 1e3:
            return
        keep = torch.isfinite(variance) & (variance > 0)
        if valid is not None:
            keep = keep & valid
        positive = variance.detach()[keep]
        if positive.numel() == 0:
            return
        low, high = float(positive.min()), float(positive.max())
    else:
        if not (0 < variance < float("inf")):
            return
        low = high = float(variance)
    if low < info.tiny or high > info.max / 1e3:
        value = low if low < info.tiny else high
        raise ValueError(
            f"{name} must lie within {info.tiny:.3g} to {info.max / 1e3:.3g} to be held in {dtype}, got {value:.3g}; "
            f"pass float64 images (.double()) or rescale the images and their variance"
        )


def check_variance_weighs(name: str, variance: Tensor, values: Tensor, valid: Tensor | None) -> None:
    """Raise ``ValueError`` if a variance whose gradient is wanted is too small for its dtype (ECR's weights).

    ``variance`` and ``values`` ``(B, N)`` (broadcast), ``valid`` bool or ``None``. Each pixel weighs ``1 / variance``
    and the gradient in the variance holds ``1 / variance^2`` times squared values summed over the ``N`` pixels: it
    must stay 1e3 below the dtype's largest value, so the variance must be at least ``max(|value|, 1) * sqrt(1e3 N /
    max)`` (7e-15 for float32 images of 256 grey levels of 16 x 16 pixels, 1e-149 in float64). The score and the
    gradient in the images stay finite below that; only a variance that takes a gradient is checked. A value check.
    """
    if not _values_checked(variance):
        return
    keep = torch.isfinite(values) & torch.isfinite(variance).expand_as(values)
    if valid is not None:
        keep = keep & valid
    if not bool(keep.any()):
        return
    scale = max(float(values.detach()[keep].abs().max()), 1.0)
    low = scale * math.sqrt(1e3 * values.shape[-1] / torch.finfo(variance.dtype).max)
    smallest = float(variance.detach().expand_as(values)[keep].min())
    if smallest < low:
        raise ValueError(
            f"{name} must be at least {low:.3g} in {variance.dtype} for values up to {scale:.3g} over "
            f"{values.shape[-1]} pixels, got {smallest:.3g}: each pixel weighs 1 / {name} and the gradient "
            f"1 / {name}^2, which would overflow; pass float64 images (.double()) or a larger {name}"
        )


def check_positive_where(name: str, values: Tensor, valid: Tensor | None) -> None:
    """Raise ``ValueError`` if ``values`` is not finite and > 0 at a valid position (a value check)."""
    if not _values_checked(values):
        return
    bad = ~(torch.isfinite(values) & (values > 0))
    if valid is not None:
        bad = bad & valid
    if bool(bad.any()):
        worst = values[bad].flatten()[0].item()
        raise ValueError(
            f"{name} must be finite and > 0 where valid_mask is True, got {int(bad.sum())} value(s) "
            f"outside that (e.g. {worst})"
        )


def check_mask_not_empty(name: str, valid: Tensor) -> None:
    """Raise ``ValueError`` if a sample of the ``(B, N)`` mask selects no pixel (a value check)."""
    if not _values_checked(valid):
        return
    empty = ~valid.any(dim=-1)
    if bool(empty.any()):
        samples = torch.nonzero(empty).flatten().tolist()
        raise ValueError(f"{name} selects no pixel in sample(s) {samples}; every sample needs at least one pixel")


def check_some_pixel(name: str, valid: Tensor, reason: str) -> None:
    """Raise ``ValueError`` if the mask ``valid`` selects no pixel at all (a value check); ``reason`` says why not."""
    if _values_checked(valid) and not bool(valid.any()):
        raise ValueError(f"{name} selects no pixel, got an all-False mask of shape {tuple(valid.shape)}: {reason}")


def check_no_overflow(name: str, result: Tensor, cause: str) -> None:
    """Raise ``ValueError`` if ``result`` holds inf or NaN that finite inputs overflowed into (a value check)."""
    if _values_checked(result) and not bool(torch.isfinite(result).all()):
        raise ValueError(f"{name} overflows {result.dtype} (largest {torch.finfo(result.dtype).max:.3g}): {cause}")


def check_log_prior(log_prior: Any, bins: int, batch: int) -> Tensor:
    """Raise unless ``log_prior`` is a float ``(bins,)``, ``(1, bins)`` or ``(batch, bins)`` without NaN or +inf.

    Returns it as ``(1 or batch, 1, bins)``; ``-inf`` (a bin the prior rules out) is allowed.
    """
    check_floating("log_prior", log_prior)
    if log_prior.shape not in ((bins,), (1, bins), (batch, bins)):
        raise ValueError(
            f"log_prior must have shape ({bins},), (1, {bins}) or ({batch}, {bins}), got {tuple(log_prior.shape)}"
        )
    if log_prior.device.type == "cpu" and bool(torch.isnan(log_prior).any() | torch.isposinf(log_prior).any()):
        raise ValueError("log_prior must hold finite values or -inf, got NaN or +inf")
    return log_prior.reshape(-1, 1, bins)


def check_captured_in_reference(captured: Any, reference: Any, reference_dims: str) -> tuple[int, int, int]:
    """Raise unless ``captured`` is ``(B, 1, h, w)`` and ``reference`` ``(1 or B, 1, H, W)``, ``H >= h``, ``W >= w``.

    Both must be floating point, hold data (no meta tensor) and be on one device; ``reference_dims`` names the
    reference's sizes in messages (``"Hw, Ww"``).
    Returns ``(B, h, w)``.
    """
    check_floating("captured", captured)
    check_real_data("captured", captured)
    if captured.ndim != 4 or captured.shape[1] != 1:
        raise ValueError(f"captured must have shape (B, 1, h, w), got {tuple(captured.shape)}")
    check_not_empty("captured", captured)
    check_floating("reference", reference)
    check_real_data("reference", reference)
    batch, _, height, width = captured.shape
    if reference.ndim != 4 or reference.shape[1] != 1 or reference.shape[0] not in (1, batch):
        raise ValueError(
            f"reference must have shape (1, 1, {reference_dims}) or ({batch}, 1, {reference_dims}) for captured of "
            f"batch {batch}, got {tuple(reference.shape)}"
        )
    if reference.shape[2] < height or reference.shape[3] < width:
        raise ValueError(
            f"captured must not be larger than reference: reference must be at least as large as captured in both "
            f"dimensions, got captured {(height, width)} and reference {tuple(reference.shape[2:])}"
        )
    if reference.device != captured.device:
        raise ValueError(f"reference must be on the device of captured ({captured.device}), got {reference.device}")
    return batch, height, width


def check_real_data(name: str, value: Tensor) -> None:
    """Raise ``ValueError`` if the tensor ``value`` is a meta tensor (a shape without data) or complex."""
    if value.is_meta:
        raise ValueError(
            f"{name} must hold data, got a meta tensor (a shape only) of shape {tuple(value.shape)}: pass {name} on "
            "a device that holds values (cpu, cuda)"
        )
    if value.is_complex():
        raise TypeError(f"{name} must be real, got complex dtype {value.dtype}")


def check_same_device(name: str, value: Any, like_name: str, like: Any) -> None:
    """Raise ``ValueError`` unless the tensors ``value`` and ``like`` hold data on one device (named in the message).

    Tensors only (anything else is left to the type checks); meta tensors are refused by name.
    """
    if not isinstance(value, Tensor) or not isinstance(like, Tensor):
        return
    check_real_data(like_name, like)
    check_real_data(name, value)
    if value.device != like.device:
        raise ValueError(f"{name} must be on the device of {like_name} ({like.device}), got {value.device}")


def check_counts(name: str, counts: Tensor) -> None:
    """Raise ``ValueError`` if the histogram ``counts`` hold a NaN, an inf or a negative count (a value check)."""
    if not _values_checked(counts):
        return
    bad = ~torch.isfinite(counts) | (counts < 0)
    if bool(bad.any()):
        worst = counts[bad].flatten()[0].item()
        raise ValueError(f"{name} must be finite counts >= 0, got {int(bad.sum())} value(s) outside (e.g. {worst})")


def check_log_prior_allows_a_bin(log_prior: Tensor) -> None:
    """Raise ``ValueError`` if a row of the ``(..., bins)`` ``log_prior`` is ``-inf`` everywhere (no bin allowed)."""
    if not _values_checked(log_prior):
        return
    ruled_out = torch.isneginf(log_prior).all(-1)
    if bool(ruled_out.any()):
        raise ValueError(
            f"log_prior must allow at least one bin (a value above -inf) in each row, got {int(ruled_out.sum())} "
            "row(s) of -inf only"
        )
