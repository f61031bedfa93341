"""Normalised cross-correlation (Pearson) over the valid pixels: the classic score of a linear sensor response.

Model (:ref:`model-ncc`): Pearson's correlation of the captured and reference values over the valid pixels, the
score of a linear response with one noise level everywhere; ``ECR(response="linear")`` is its noise-aware form.

:func:`ncc` of aligned pairs, :func:`ncc_surface` over every placement (six FFT correlations of masks, centred images
and their squares: :func:`~enmi_torch.placement.planes.moment_blocks`), :func:`ncc_loss` (``1 - NCC``) and
:class:`NCC`. It takes no variance and no bins.
"""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.histogram import prepare_inputs
from enmi_torch.placement.inputs import Surface, SurfaceInputs, check_inputs
from enmi_torch.placement.planes import masked_mean, moment_blocks
from enmi_torch.scores.base import LeastSquaresFit, ResponseBasis, Score, reduce_loss
from enmi_torch.utils.budget import check_surface_memory


def ncc(captured: Tensor, reference: Tensor, *, valid_mask: Tensor | None = None) -> Tensor:
    """Pearson correlation of each captured/reference pair over its valid pixels, ``(B,)``.

    Args:
        captured: ``(B, 1, H, W)`` or ``(B, H, W)`` (flat samples: ``(B, 1, N)``), floating point.
        reference: same shape as ``captured``, or ``(C, *captured.shape)`` for ``C`` candidates per captured image.
        valid_mask: bool ``(H, W)``, ``(1, 1, H, W)`` or ``(B, 1, H, W)``; ``False`` pixels are left out (they may
            hold NaN).

    Returns:
        ``(B,)`` (``(C, B)`` for candidates) in ``[-1, 1]``, same dtype as ``captured``; 0 where fewer than two pixels
        are valid or either side is constant over them.

    Convention:
        Differentiable in ``captured`` and ``reference``.

    Example:
        >>> captured = torch.tensor([[[1.0, 2.0, 3.0, 4.0]]])  # one flat sample (1, 1, N)
        >>> ncc(captured, captured**2), ncc(captured, -captured)
        (tensor([0.9844]), tensor([-1.]))
    """
    # The layout and mask checks of the histograms; nothing is binned (bins and range only fill masked pixels).
    inputs = prepare_inputs(
        captured,
        reference,
        2,
        (0.0, 1.0),
        None,
        valid_mask,
        "hard",
        "hard",
        None,
        captured_binned=False,
        reference_binned=False,
    )
    weight = torch.ones_like(inputs.captured) if inputs.pair_weight is None else inputs.pair_weight
    count = weight.sum(-1, keepdim=True)

    # Pearson does not see a positive scale: dividing values whose squares could overflow (1e30 in float32) by their
    # largest valid magnitude keeps the score from collapsing to 0; other values are left as they are (no rounding).
    large = torch.finfo(inputs.captured.dtype).max ** 0.5 / 1e4

    def centred(values: Tensor) -> Tensor:
        scale = (values.detach().abs() * weight).amax(-1, keepdim=True)
        values = values / torch.where(scale > large, scale, 1.0)
        return (values - (values * weight).sum(-1, keepdim=True) / count.clamp_min(1)) * weight

    captured_centred, reference_centred = centred(inputs.captured), centred(inputs.reference)
    covariance = (captured_centred * reference_centred).sum(-1)
    spread = captured_centred.square().sum(-1) * reference_centred.square().sum(-1)
    defined = (count[..., 0] >= 2) & (spread > 0)
    score = torch.where(defined, covariance / torch.where(defined, spread, 1.0).sqrt(), 0.0)
    return (score if inputs.with_candidates else score[0]).to(inputs.out_dtype)


def ncc_surface(
    captured: Tensor,
    reference: Tensor,
    *,
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
) -> Surface:
    """Normalised cross-correlation (Pearson) of ``captured`` at every placement inside ``reference``, masked, by FFT.

    Args:
        captured: captured image ``(B, 1, h, w)``, floating point.
        reference: map section ``(1 or B, 1, Hw, Ww)``, ``Hw >= h``, ``Ww >= w``.
        captured_mask: bool ``(h, w)``, ``(1, 1, h, w)`` or ``(B, 1, h, w)``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference.

    Returns:
        :class:`Surface`; ``score`` in ``[-1, 1]``, the Pearson correlation over the overlapping valid pixels; 0
        where fewer than two pixels overlap or either side is constant there.

    Example:
        >>> reference = torch.arange(64.0).reshape(1, 1, 8, 8) ** 1.5
        >>> round(ncc_surface(reference[..., 2:6, 1:5], reference).score[0, 2, 1].item(), 4)
        1.0
    """
    inputs = check_inputs(captured, reference, captured_mask, reference_mask, (0.0, 1.0))
    check_surface_memory(inputs.captured, inputs.reference, None)
    with torch.no_grad():
        return _ncc_surface(inputs)


def _ncc_surface(inputs: SurfaceInputs) -> Surface:
    """Masked Pearson correlation from six correlations of masks, centred images and their squares."""
    eps = torch.finfo(inputs.captured.dtype).eps
    captured_valid = inputs.captured_valid.to(inputs.captured.dtype)
    # Centring on the image's own valid mean keeps the sums small, so the FFT round-off stays relative.
    captured = (inputs.captured - masked_mean(inputs.captured, captured_valid)) * captured_valid
    scores, overlaps = [], []
    for block in moment_blocks(inputs, torch.stack([captured_valid, captured, captured.square()], dim=1)):
        count = block[0, 0].round()
        local_sum, window_sum = block[1, 0], block[0, 1]
        local_square, window_square, cross = block[2, 0], block[0, 2], block[1, 1]
        safe_count = count.clamp_min(1)
        covariance = cross - local_sum * window_sum / safe_count
        local_spread = local_square - local_sum.square() / safe_count
        window_spread = window_square - window_sum.square() / safe_count
        # A spread within round-off of its raw second moment means a constant overlap: no correlation defined.
        defined = (count >= 2) & (local_spread > 64 * eps * local_square) & (window_spread > 64 * eps * window_square)
        denominator = torch.where(defined, local_spread * window_spread, 1.0).sqrt()
        scores.append(torch.where(defined, covariance / denominator, 0.0).clamp(-1, 1))
        overlaps.append(count)
    return Surface(torch.stack(scores), torch.stack(overlaps))


def ncc_loss(
    captured: Tensor,
    reference: Tensor,
    *,
    valid_mask: Tensor | None = None,
    reduction: str = "mean",
) -> Tensor:
    """``1 - ncc(captured, reference)`` reduced over the batch (0 when aligned), in ``[0, 2]``: ``NCC().loss(...)``.

    Example:
        >>> captured = torch.tensor([[[1.0, 2.0, 3.0, 4.0]]])  # one flat sample (1, 1, N)
        >>> ncc_loss(captured, 2 * captured + 1), ncc_loss(captured, -captured)
        (tensor(0.), tensor(2.))
    """
    return NCC().loss(captured, reference, valid_mask=valid_mask, reduction=reduction)


class NCC(Score):
    """NCC as an object: :func:`ncc`, :func:`ncc_surface` and :func:`ncc_loss` (no options).

    Example:
        >>> captured = torch.tensor([[[1.0, 2.0, 3.0, 4.0]]])  # one flat sample (1, 1, N)
        >>> NCC()(captured, 2 * captured + 1), NCC().loss(captured, 2 * captured + 1)
        (tensor([1.]), tensor(0.))
    """

    name = "ncc"
    uses_variance = False
    trait_holders = frozenset({"least_squares"})

    def __init__(self) -> None:
        super().__init__()

    def _value(self, captured, reference, variance, valid_mask) -> Tensor:
        return ncc(captured, reference, valid_mask=valid_mask)

    def _surface(self, captured, reference, variance, captured_mask, reference_mask) -> Surface:
        return ncc_surface(captured, reference, captured_mask=captured_mask, reference_mask=reference_mask)

    def _loss(self, captured, reference, variance, valid_mask, reduction) -> Tensor:
        return reduce_loss(1 - self._value(captured, reference, variance, valid_mask), reduction)

    @property
    def traits(self) -> frozenset[str]:
        """``"least_squares"``: :func:`~enmi_torch.register` fits the affine response."""
        return frozenset({"least_squares"})

    def response_basis(self) -> ResponseBasis:
        """The affine response ``a + b m``: NCC squared is the share of the variance it explains."""
        return ResponseBasis()

    def least_squares_fit(
        self, captured: Tensor, reference: Tensor, variance: Tensor | None, valid: Tensor
    ) -> LeastSquaresFit:
        """Every valid pixel weighs alike (1), the response is fitted freely."""
        return LeastSquaresFit(valid.reshape(captured.shape[0], -1).to(captured.dtype))
