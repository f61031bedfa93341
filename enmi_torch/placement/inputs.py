"""The checked inputs of a surface over every placement, and the :class:`Surface` it gives.

Convention:
    ``captured`` is ``(B, 1, h, w)``; ``reference`` is ``(1, 1, Hw, Ww)`` (shared) or ``(B, 1, Hw, Ww)``, with
    ``Hw >= h`` and ``Ww >= w``. A surface is ``(B, Hw - h + 1, Ww - w + 1)``: entry ``[b, u, v]`` scores the captured
    image with its top-left pixel on reference cell ``(u, v)`` (row, column). Masked pixels of either image are left
    out of that placement; ``overlap`` counts the captured pixels that remain.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.utils.checks import (
    check_captured_in_reference,
    check_finite_where,
    check_magnitude,
    check_resolved_by_bins,
)
from enmi_torch.utils.layout import mask_map, variance_map


class Surface(NamedTuple):
    """A dense score surface and the overlap behind each entry.

    Attributes:
        score: ``(B, Sy, Sx)`` score per placement.
        overlap: ``(B, Sy, Sx)`` number of valid captured pixels that land on valid reference cells (integer-valued).
        scored: ``(B, Sy, Sx)`` bool: the placements whose ``score`` holds the family's value, the others ``-inf``
            (a surface that scores a few placements exactly and ranks the rest by a cheap score, such as the
            mixture score's); ``None``: every placement is scored.
    """

    score: Tensor
    overlap: Tensor
    scored: Tensor | None = None


class SurfaceInputs(NamedTuple):
    """Checked surface inputs in the compute dtype (float64 for float64 captured images, float32 otherwise)."""

    captured: Tensor  # (B, h, w), masked pixels set to the low end of the range
    reference: Tensor  # (Bw, Hw, Ww), masked cells set to the low end of the range
    captured_valid: Tensor  # (B, h, w) bool
    reference_valid: Tensor  # (Bw, Hw, Ww) bool
    variance: Tensor | None  # (B, h, w), 1 where masked


def check_inputs(
    captured: Tensor,
    reference: Tensor,
    captured_mask: Tensor | None,
    reference_mask: Tensor | None,
    value_range: tuple[float, float],
    variance: Tensor | float | None = None,
    bins: int | None = None,
    reference_bins: int | None = None,
) -> SurfaceInputs:
    """Shapes, masks and values checked; images as ``(B, h, w)`` and ``(Bw, Hw, Ww)`` in the compute dtype.

    With ``bins`` (the captured image is binned) a captured image whose values all fall in one bin while varying is
    refused; with ``reference_bins`` (the reference is binned, as by ECR) a reference image alike.
    """
    batch, height, width = check_captured_in_reference(captured, reference, "Hw, Ww")
    dtype = torch.float64 if captured.dtype == torch.float64 else torch.float32
    local_flat = captured.reshape(batch, -1).to(dtype)
    window_flat = reference.reshape(reference.shape[0], -1).to(dtype)

    captured_valid = _mask("captured_mask", captured_mask, captured)
    reference_valid = _mask("reference_mask", reference_mask, reference)
    check_finite_where("captured", local_flat, captured_valid, "captured_mask")
    check_finite_where("reference", window_flat, reference_valid, "reference_mask")
    check_magnitude("captured", local_flat, captured_valid, "captured_mask")
    check_magnitude("reference", window_flat, reference_valid, "reference_mask")
    if bins is not None:
        check_resolved_by_bins("captured", local_flat, captured_valid, bins, value_range)
    if reference_bins is not None:
        check_resolved_by_bins("reference", window_flat, reference_valid, reference_bins, value_range)
    local_flat = torch.where(captured_valid, local_flat, value_range[0])
    window_flat = torch.where(reference_valid, window_flat, value_range[0])
    variance_flat = None
    if variance is not None:
        variance_flat = variance_map("variance", variance, captured, dtype, captured_valid).reshape(
            batch, height, width
        )
    return SurfaceInputs(
        local_flat.reshape(batch, height, width),
        window_flat.reshape(reference.shape[0], *reference.shape[2:]),
        captured_valid.reshape(batch, height, width),
        reference_valid.reshape(reference.shape[0], *reference.shape[2:]),
        variance_flat,
    )


def _mask(name: str, mask: Tensor | None, like: Tensor) -> Tensor:
    """A bool mask as ``(B, N)`` for ``like``'s batch; all ``True`` when ``None``; raises if a sample selects none."""
    if mask is None:
        return torch.ones(like.shape[0], like[0].numel(), dtype=torch.bool, device=like.device)
    return mask_map(name, mask, like, "captured" if name == "captured_mask" else "reference")
