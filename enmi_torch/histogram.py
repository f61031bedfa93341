"""Joint histograms of a captured image against a reference (map) image, hard, Parzen or likelihood-weighted.

The joint histogram is the streaming state of every score here: its counts add across batches, chunks and
processes, and :func:`~enmi_torch.information.nmi_from_joint_histogram` turns the sum into a score.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.binning import (
    LIKELIHOOD_WEIGHTS,
    PARZEN_KERNELS,
    bin_edges,
    hard_bin_index,
    likelihood_weights_unchecked,
    likelihood_weights_vjp,
    mass_weights_vjp,
    min_variance,
    parzen_weights_unchecked,
)
from enmi_torch.utils.budget import check_histogram_memory
from enmi_torch.utils.checks import (
    check_bins,
    check_finite_where,
    check_floating,
    check_log_prior,
    check_option,
    check_resolved_by_bins,
    check_same_device,
    check_tensor,
    check_value_range,
    check_variance_weighs,
)
from enmi_torch.utils.layout import flatten_image, mask_map, scalar_or_map, variance_map

CAPTURED_KERNELS = PARZEN_KERNELS + LIKELIHOOD_WEIGHTS

# Pixels per chunk are chosen so one chunk's (B, n, bins) weights stay near this many elements: on CPU 1 MiB in
# float32, which keeps a chunk's temporaries in cache; on accelerators larger chunks amortise the kernel launches.
_CHUNK_ELEMENTS = 1 << 18
_ACCELERATOR_CHUNK_ELEMENTS = 1 << 20
# Hard entropies count pixels in a table of every cell up to this many cells (or 16 per pixel), else by sorting.
_TABLE_CELLS = 1 << 20


def joint_histogram(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float | None = None,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    valid_mask: Tensor | None = None,
    kernel: str | None = None,
    reference_kernel: str = "hard",
    log_prior: Tensor | None = None,
    pixel_weight: Tensor | None = None,
    captured_variance: Tensor | float | None = None,
) -> Tensor:
    """Joint histogram (counts) of a captured image and a reference image, ``(B, bins, bins)``.

    Args:
        captured: captured (sensor) image ``(B, 1, H, W)`` or ``(B, H, W)`` (flat samples: ``(B, 1, N)``), floating.
        reference: reference (map) image of the same shape, or ``C`` candidate references per captured image,
            ``(C, *captured.shape)``: each captured image is then histogrammed against each candidate, its pixel
            weights computed once (the costly part of the likelihood kernels), and the result is
            ``(C, B, bins, bins)``.
        variance: per-pixel noise variance of ``captured`` (> 0 where valid): a number, ``(H, W)``,
            ``(1, 1, H, W)`` or ``(B, 1, H, W)`` (likewise for the other layouts). Required by the likelihood
            kernels ``"mass"``/``"density"``, refused by the others. The third argument, as in every score.
        bins: number of equal-width amplitude bins, >= 2.
        value_range: ``(low, high)`` covered by the bins; values outside are clipped into the edge bins.
        valid_mask: bool, same broadcasting as ``variance``; ``False`` pixels are left out (they may hold
            NaN). ``None`` keeps every pixel.
        kernel: how a captured pixel spreads its unit weight over the bins: ``"hard"``, ``"triangular"``, ``"xu"``
            (Parzen windows, see :func:`~enmi_torch.binning.parzen_weights`) or ``"mass"``, ``"density"``
            (Gaussian likelihood, see :func:`~enmi_torch.binning.likelihood_weights`). ``None``: ``"mass"`` when a
            variance is given, else ``"hard"``.
        reference_kernel: ``"hard"`` (the noiseless map, default), ``"triangular"`` or ``"xu"`` (soft, so the
            reference gets a gradient).
        log_prior: optional log prior of the amplitude per bin, ``(bins,)`` or ``(B, bins)``, for the likelihood
            kernels (MAP weights). Not differentiated.
        pixel_weight: optional weight >= 0 of each captured pixel (e.g.
            :func:`~enmi_torch.binning.reliability_weights`), broadcast like ``variance``: a valid pixel adds
            this total weight instead of 1. Not differentiated; takes the dense (autograd) path.
        captured_variance: the former name of ``variance`` (keyword only), still accepted.

    Returns:
        Counts ``(B, bins, bins)`` (``(C, B, bins, bins)`` for candidates): captured bins on axis -2, reference
        bins on axis -1. Each valid pixel adds a
        total weight of 1, so a sample's counts sum to its number of valid pixels. Same dtype as ``captured``
        (half precision is accumulated in float32 and cast back).

    Raises:
        MemoryBudgetError: before allocating, when the ``(C, B, bins, bins)`` counts (and the dense bin weights of
            the Parzen kernels) would exceed the memory budget, 4 GiB unless raised with
            :func:`~enmi_torch.utils.budget.set_memory_budget` or :func:`~enmi_torch.utils.budget.memory_budget`.

    Convention:
        Gradients flow to ``captured`` and ``variance`` for the differentiable kernels and to
        ``reference`` for soft reference kernels. With a hard reference and a likelihood kernel the histogram is
        accumulated in chunks by a custom autograd function that never stores the ``(B, N, bins)`` weights.

    Example:
        >>> captured = torch.tensor([[[0.5, 1.5, 2.5, 3.5]]])  # one flat sample (1, 1, N)
        >>> joint_histogram(captured, captured, bins=2, value_range=(0, 4))
        tensor([[[2., 0.],
                 [0., 2.]]])
        >>> candidates = torch.stack([captured, captured.flip(-1)])
        >>> joint_histogram(captured, candidates, bins=2, value_range=(0, 4))[1]
        tensor([[[0., 2.],
                 [2., 0.]]])
    """
    if captured_variance is not None:
        if variance is not None:
            raise TypeError("joint_histogram takes variance or its former name captured_variance, got both")
        variance = captured_variance
    inputs = prepare_inputs(
        captured, reference, bins, value_range, variance, valid_mask, kernel, reference_kernel, log_prior
    )
    if pixel_weight is not None:
        inputs = with_pixel_weight(inputs, pixel_weight, captured)
    return joint_histogram_of_inputs(inputs)


def with_pixel_weight(inputs: HistogramInputs, pixel_weight: Tensor | float, captured: Tensor) -> HistogramInputs:
    """``inputs`` whose valid pixels count with ``pixel_weight`` (checked finite and >= 0 there)."""
    weight = scalar_or_map("pixel_weight", pixel_weight, captured).detach().to(inputs.captured.dtype)
    weight = weight.expand_as(inputs.captured)
    check_finite_where("pixel_weight", weight, inputs.valid)
    negative = weight < 0 if inputs.valid is None else (weight < 0) & inputs.valid
    if bool(negative.any()):
        raise ValueError("pixel_weight must be >= 0 where valid, got a negative weight")
    if inputs.pair_weight is not None:
        weight = weight * inputs.pair_weight
    return inputs._replace(pair_weight=weight, weighted=True)


def joint_histogram_of_inputs(inputs: HistogramInputs, *, scored: bool = False) -> Tensor:
    """The joint histogram of inputs checked by :func:`prepare_inputs`, after checking that it fits the memory budget.

    What :func:`joint_histogram` returns, for the scores that check their arguments once and then count
    (:func:`~enmi_torch.scores.nmi.nmi`, :func:`~enmi_torch.scores.enmi.enmi`). ``scored``: the caller turns the
    counts into entropies, which holds three more tensors of their size (counted against the budget).
    """
    reference_kernel = inputs.reference_kernel
    candidates, batch, pixels = inputs.reference.shape
    streamed = inputs.kernel in LIKELIHOOD_WEIGHTS and reference_kernel == "hard" and not inputs.weighted
    dense_weights = not streamed and (inputs.kernel, reference_kernel) != ("hard", "hard")
    check_histogram_memory(
        inputs.captured,
        inputs.bins,
        candidates if inputs.with_candidates else None,
        captured_planes=dense_weights,
        reference_planes=reference_kernel != "hard" or (dense_weights and candidates > 1),
        scored=scored,
    )
    with torch.autocast(device_type=inputs.captured.device.type, enabled=False):
        if streamed:
            rows = _reference_rows(inputs.reference, inputs.bins, inputs.value_range)
            spare_row = rows.numel() // pixels * inputs.bins
            if inputs.valid is not None:
                # Masked pixels go to a spare last row that is dropped: no multiply, and no gradient reaches them.
                rows = torch.where(inputs.valid, rows, spare_row)
            counts = _LikelihoodJointHistogram.apply(
                inputs.captured, inputs.variance, rows, inputs.log_prior, inputs.bins, inputs.value_range, inputs.kernel
            )
            counts = counts[:spare_row].view(-1, batch, inputs.bins, inputs.bins).transpose(-1, -2)
        else:
            counts = _dense_joint_histogram(
                inputs.captured,
                inputs.reference,
                inputs.variance,
                inputs.pair_weight,
                inputs.log_prior,
                inputs.bins,
                inputs.value_range,
                inputs.kernel,
                reference_kernel,
            )
    return (counts if inputs.with_candidates else counts[0]).to(inputs.out_dtype)


def hard_entropies(
    captured: Tensor,
    reference: Tensor,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    valid_mask: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Entropies ``(H[A], H[B], H[A, B])`` in nats of the hard joint histogram, read at the pixels, ``(B,)`` each.

    The same values as :func:`~enmi_torch.information.entropies` of the hard :func:`joint_histogram`, computed as
    the mean surprisal of the pixels, ``H = sum_pixels log(n / c(pixel)) / n`` with ``c(pixel)`` the count of the
    pixel's cell and ``n`` the number of valid pixels: ``O(pixels)`` logarithms per sample instead of ``O(bins^2)``.
    That pays for small images and many samples (fewer pixels than ``bins^2 / 4``, e.g. the paper's 66 road tiles
    and 32 bins), where :func:`~enmi_torch.functional.nmi` uses it.

    Args:
        captured: ``(B, 1, H, W)`` or ``(B, H, W)`` (flat samples: ``(B, 1, N)``), floating point.
        reference: same shape as ``captured``, or ``(C, *captured.shape)`` for ``C`` candidates.
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)``; values outside are clipped into the edge bins.
        valid_mask: bool, broadcast like in :func:`joint_histogram`; ``False`` pixels are left out.

    Returns:
        Three tensors ``(B,)`` (``(C, B)`` for candidates), same dtype as ``captured``; no gradient (hard bins).

    Example:
        >>> captured = torch.tensor([[[0.5, 1.5, 2.5, 3.5]]])  # one flat sample (1, 1, N)
        >>> [round(h.item(), 4) for h in hard_entropies(captured, captured.flip(-1), bins=2, value_range=(0, 4))]
        [0.6931, 0.6931, 0.6931]
    """
    inputs = prepare_inputs(captured, reference, bins, value_range, None, valid_mask, "hard", "hard", None)
    captured_bins = hard_bin_index(inputs.captured, inputs.bins, inputs.value_range)
    reference_bins = hard_bin_index(inputs.reference, inputs.bins, inputs.value_range)
    weight = inputs.captured.new_ones(inputs.captured.shape) if inputs.pair_weight is None else inputs.pair_weight
    captured_entropy = mean_surprisal(captured_bins, inputs.bins, weight).expand(inputs.reference.shape[:-1])
    reference_entropy = mean_surprisal(reference_bins, inputs.bins, weight)
    joint_entropy = mean_surprisal(captured_bins * inputs.bins + reference_bins, inputs.bins**2, weight)
    entropies = (captured_entropy, reference_entropy, joint_entropy)
    return tuple((entropy if inputs.with_candidates else entropy[0]).to(inputs.out_dtype) for entropy in entropies)


def mean_surprisal(cells: Tensor, cell_count: int, weight: Tensor) -> Tensor:
    """Entropy in nats of the cells ``(..., N)`` (in ``[0, cell_count)``) of each sample, pixels weighted by ``weight``.

    The mean surprisal ``sum_pixels weight log(total / c(pixel)) / total``, ``c(pixel)`` the summed weight of the
    pixel's cell: the entropy of the hard histogram read at the pixels (:func:`hard_entropies`), ``(...,)``.

    Example:
        >>> round(mean_surprisal(torch.tensor([[0, 0, 1, 1]]), 2, torch.ones(1, 4)).item(), 4)
        0.6931
    """
    weight = weight.expand(cells.shape)
    total = weight.sum(dim=-1, keepdim=True)
    # log n - log c: exactly 0 when c = n. Masked pixels weigh 0; the clamp keeps their log finite in empty cells.
    pixel_counts = _cell_weights(cells, cell_count, weight).clamp_min(torch.finfo(weight.dtype).tiny)
    surprisal = total.log() - pixel_counts.log_()
    return torch.linalg.vecdot(weight, surprisal) / total.squeeze(-1)


def _cell_weights(cells: Tensor, cell_count: int, weight: Tensor) -> Tensor:
    """``(..., N)``: the summed ``weight`` of the pixels in each pixel's cell, within its sample.

    A table of every cell of every sample while it stays small next to the pixels; beyond that (many bins, e.g.
    ``bins=100000`` has 1e10 joint cells) each sample's cells are sorted and the runs of equal cells summed, in
    memory linear in the pixels. Both sum the same 0/1 weights, so the counts are the same exact integers.
    """
    samples = cells.shape[:-1].numel()
    if samples * cell_count <= max(_TABLE_CELLS, 16 * cells.numel()):
        offsets = torch.arange(samples, device=cells.device).view(*cells.shape[:-1], 1) * cell_count
        flat = (cells + offsets).flatten()
        counts = weight.new_zeros(samples * cell_count).index_add_(0, flat, weight.flatten())
        return counts.index_select(0, flat).view(cells.shape)
    sorted_cells, order = cells.sort(dim=-1)
    starts = torch.ones_like(sorted_cells, dtype=torch.bool)
    starts[..., 1:] = sorted_cells[..., 1:] != sorted_cells[..., :-1]
    runs = starts.flatten().cumsum(0) - 1  # each sample starts a new run
    run_weights = weight.new_zeros(cells.numel()).index_add_(0, runs, weight.gather(-1, order).flatten())
    return torch.empty_like(weight).scatter_(-1, order, run_weights[runs].view(cells.shape))


class HistogramInputs(NamedTuple):
    """Inputs checked by :func:`prepare_inputs`, in the compute dtype.

    ``captured`` is ``(B, N)``, ``reference`` ``(C, B, N)``; ``valid`` the mask ``(B or 1, N)`` or ``None``;
    ``pair_weight`` each pixel's weight (the mask as 0/1, or real weights when ``weighted``); ``with_candidates``
    whether the caller gave ``C`` candidate references; ``out_dtype`` the dtype the result is returned in.
    """

    captured: Tensor
    reference: Tensor
    valid: Tensor | None
    pair_weight: Tensor | None
    variance: Tensor | None
    log_prior: Tensor | None
    bins: int
    value_range: tuple[float, float]
    kernel: str
    reference_kernel: str
    with_candidates: bool
    out_dtype: torch.dtype
    # True when pair_weight holds real per-pixel weights (reliability), not a 0/1 mask: the dense path takes them.
    weighted: bool = False


def prepare_inputs(
    captured,
    reference,
    bins,
    value_range,
    captured_variance,
    valid_mask,
    kernel,
    reference_kernel,
    log_prior,
    variance_name="captured_variance",
    captured_binned=True,
    reference_binned=True,
) -> HistogramInputs:
    """Check the arguments of :func:`joint_histogram` and bring them to the flat layout and compute dtype.

    The scores built on histograms (NMI, ENMI, ECR, NCC, the mixture score) check their arguments here once, with the
    same messages; returns :class:`HistogramInputs` for :func:`joint_histogram_of_inputs`.

    ``variance_name`` is the name the caller's users give ``captured_variance`` (``"variance"`` for ENMI);
    ``captured_binned``: the captured values are binned (not for ECR), so they must not all fall in one bin;
    ``reference_binned``: the reference is binned (not for NCC): for ECR, whose captured values are not binned, it
    must not all fall in one bin either.
    """
    check_floating("captured", captured)
    check_tensor("reference", reference)
    check_same_device("reference", reference, "captured", captured)
    check_same_device(variance_name, captured_variance, "captured", captured)
    with_candidates = reference.ndim == captured.ndim + 1 and reference.shape[1:] == captured.shape
    if reference.shape != captured.shape and not with_candidates:
        raise ValueError(
            f"reference must have the shape of captured {tuple(captured.shape)} or (C, *that shape) for C candidates, "
            f"got {tuple(reference.shape)}"
        )
    check_floating("reference", reference)
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    if kernel is None:
        kernel = "hard" if captured_variance is None else "mass"
    check_option("kernel", kernel, CAPTURED_KERNELS)
    check_option("reference_kernel", reference_kernel, PARZEN_KERNELS)
    if kernel in LIKELIHOOD_WEIGHTS and captured_variance is None:
        raise ValueError(f"kernel={kernel!r} needs {variance_name}, got None")
    if kernel not in LIKELIHOOD_WEIGHTS and captured_variance is not None:
        raise ValueError(f"{variance_name} is only used by kernels {list(LIKELIHOOD_WEIGHTS)}, got kernel={kernel!r}")
    if log_prior is not None and kernel not in LIKELIHOOD_WEIGHTS:
        raise ValueError(f"log_prior is only used by kernels {list(LIKELIHOOD_WEIGHTS)}, got kernel={kernel!r}")

    out_dtype = captured.dtype
    compute_dtype = torch.float64 if out_dtype == torch.float64 else torch.float32
    captured_flat = flatten_image("captured", captured).to(compute_dtype)
    batch, pixels = captured_flat.shape
    reference_flat = reference.reshape(-1, batch, pixels).to(compute_dtype)
    if reference_flat.shape[0] == 0:
        raise ValueError(f"reference must hold at least one candidate, got shape {tuple(reference.shape)}")

    valid = None if valid_mask is None else mask_map("valid_mask", valid_mask, captured)
    check_finite_where("captured", captured_flat, valid)
    check_finite_where("reference", reference_flat, valid)
    if captured_binned:
        check_resolved_by_bins("captured", captured_flat, valid, bins, value_range)
    elif reference_binned:  # ECR bins the reference: a map varying within one bin would score 0 everywhere
        flat_valid = None if valid is None else valid.expand_as(reference_flat).reshape(-1, pixels)
        check_resolved_by_bins("reference", reference_flat.reshape(-1, pixels), flat_valid, bins, value_range)
    if valid is not None:
        # Masked pixels may hold NaN (out-of-range regions): replace them so 0 * NaN never reaches the counts.
        captured_flat = torch.where(valid, captured_flat, value_range[0])
        reference_flat = torch.where(valid, reference_flat, value_range[0])
    pair_weight = None if valid is None else valid.to(compute_dtype)
    variance = None
    if captured_variance is not None:
        variance = variance_map(variance_name, captured_variance, captured, compute_dtype, valid)
        if not captured_binned and variance.requires_grad:  # ECR: 1 / variance^2 in the variance's gradient
            check_variance_weighs(variance_name, variance, captured_flat, valid)
    if log_prior is not None:
        log_prior = check_log_prior(log_prior, bins, batch).to(captured_flat.device, compute_dtype)

    return HistogramInputs(
        captured_flat,
        reference_flat,
        valid,
        pair_weight,
        variance,
        log_prior,
        bins,
        value_range,
        kernel,
        reference_kernel,
        with_candidates,
        out_dtype,
    )


def _reference_rows(reference: Tensor, bins: int, value_range: tuple[float, float]) -> Tensor:
    """Row of each pixel of a ``(..., B, N)`` reference in the transposed histogram ``(... * B * bins, bins)``.

    The row is ``s * bins + reference bin``, ``s`` the flat index of the sample (candidate-major).
    """
    samples = reference.shape[:-1].numel()
    offsets = torch.arange(samples, device=reference.device).view(*reference.shape[:-1], 1) * bins
    return hard_bin_index(reference, bins, value_range) + offsets


def _chunks(batch: int, pixels: int, bins: int, device: torch.device):
    elements = _CHUNK_ELEMENTS if device.type == "cpu" else _ACCELERATOR_CHUNK_ELEMENTS
    step = max(1, elements // (batch * bins))
    for start in range(0, pixels, step):
        yield slice(start, min(start + step, pixels))


def _pixel_weights(captured, variance, pair_weight, log_prior, bins, value_range, kernel) -> Tensor:
    """``(B, n, bins)`` weights of the captured pixels, zero rows where masked."""
    if kernel in LIKELIHOOD_WEIGHTS:
        weights = likelihood_weights_unchecked(captured, variance, bins, value_range, kernel, log_prior)
    else:
        weights = parzen_weights_unchecked(captured, bins, value_range, kernel)
    return weights if pair_weight is None else weights * pair_weight.unsqueeze(-1)


def _dense_joint_histogram(
    captured, reference, variance, pair_weight, log_prior, bins, value_range, kernel, reference_kernel
) -> Tensor:
    """Plain autograd path: ``(B, N, bins)`` captured weights, then a product with each ``(..., B, N)`` reference.

    Returns ``(..., B, bins, bins)``, the leading dimensions those of ``reference`` (candidates).
    """
    if kernel == "hard" and reference_kernel == "hard":
        return _hard_joint_histogram(captured, reference, pair_weight, bins, value_range)
    captured_weights = _pixel_weights(captured, variance, pair_weight, log_prior, bins, value_range, kernel)
    if reference_kernel == "hard":
        rows = _reference_rows(reference, bins, value_range).flatten()
        source = captured_weights.expand(*reference.shape, bins).reshape(-1, bins)
        transposed = captured_weights.new_zeros(reference.shape[:-1].numel() * bins, bins).index_add(0, rows, source)
        return transposed.view(*reference.shape[:-1], bins, bins).transpose(-1, -2)
    reference_weights = parzen_weights_unchecked(reference, bins, value_range, reference_kernel)
    return torch.matmul(captured_weights.transpose(-1, -2), reference_weights)


def _hard_joint_histogram(captured, reference, pair_weight, bins, value_range) -> Tensor:
    """Unit counts added into ``(sample, captured bin, reference bin)`` cells (no gradient).

    ``captured`` is ``(B, N)``, ``reference`` ``(..., B, N)``; returns ``(..., B, bins, bins)``. ``index_add_``
    rather than ``bincount``: on CUDA ``bincount`` reads the largest index back to the host.
    """
    samples = reference.shape[:-1]
    offsets = torch.arange(samples.numel(), device=captured.device).view(*samples, 1) * (bins * bins)
    cells = hard_bin_index(captured, bins, value_range) * bins + hard_bin_index(reference, bins, value_range) + offsets
    weights = captured.new_ones(()) if pair_weight is None else pair_weight
    counts = captured.new_zeros(samples.numel() * bins * bins)
    counts.index_add_(0, cells.flatten(), weights.expand(reference.shape).flatten())
    return counts.view(*samples, bins, bins)


def _twice_mass_weights(values: Tensor, variance: Tensor, bins: int, value_range: tuple[float, float]) -> Tensor:
    """Twice the ``"mass"`` weights of :func:`likelihood_weights` in four in-place passes (the hot loop).

    ``2 Phi(z) = 1 + erf(z / sqrt 2)``, so differences of erf at the interior edges are twice the bin masses; the
    caller halves the accumulated counts once instead of every weight.
    """
    inverse_scale = variance.clamp_min(min_variance(bins, value_range)).mul(2).rsqrt_().unsqueeze(-1)
    interior = bin_edges(bins, value_range, dtype=values.dtype, device=values.device)[1:-1]
    edge_erf = (interior - values.unsqueeze(-1)).mul_(inverse_scale).erf_()
    weights = torch.empty(*values.shape, bins, dtype=values.dtype, device=values.device)
    torch.sub(edge_erf[..., 1:], edge_erf[..., :-1], out=weights[..., 1:-1])
    torch.add(edge_erf[..., 0], 1, out=weights[..., 0])
    torch.sub(1, edge_erf[..., -1], out=weights[..., -1])
    return weights


def likelihood_counts(
    captured: Tensor,
    variance: Tensor,
    rows: Tensor,
    log_prior: Tensor | None,
    bins: int,
    value_range: tuple[float, float],
    kernel: str,
    *,
    normalized_later: bool = False,
) -> Tensor:
    """The transposed likelihood-weighted histogram ``(C * B * bins + 1, bins)`` of checked inputs, without autograd.

    The forward pass of :class:`_LikelihoodJointHistogram` (see there for ``rows``), for callers that check their
    inputs once and score many batches (the paper's simulation). ``normalized_later``: the caller only uses the
    counts divided by their sum, so the ``"mass"`` weights skip their exact halving (the same probabilities, bit
    for bit).
    """
    batch, pixels = captured.shape
    transposed = captured.new_zeros(rows.shape[0] * batch * bins + 1, bins)
    for part in _chunks(batch, pixels, bins, captured.device):
        if kernel == "mass" and log_prior is None:
            weights = _twice_mass_weights(captured[:, part], variance[:, part], bins, value_range)
        else:
            weights = likelihood_weights_unchecked(
                captured[:, part], variance[:, part], bins, value_range, kernel, log_prior
            )
        weights = weights.reshape(-1, bins)
        for candidate_rows in rows:
            transposed.index_add_(0, candidate_rows[:, part].reshape(-1), weights)
    if kernel == "mass" and log_prior is None and not normalized_later:
        transposed.mul_(0.5)
    return transposed


class _LikelihoodJointHistogram(torch.autograd.Function):
    """Likelihood-weighted captured pixels added to the rows of hard-binned references, in chunks.

    ``rows`` ``(C, B, N)`` holds ``(c * B + b) * bins + reference bin`` per pixel of each of ``C`` references, or
    the spare row ``C * B * bins`` for masked pixels; the result is the transposed histogram
    ``(C * B * bins + 1, bins)``. Each chunk's captured weights are computed once and added for every reference.
    Backward recomputes each chunk from the saved inputs with the closed-form
    :func:`~enmi_torch.binning.likelihood_weights_vjp` (linear in the upstream gradient, so the references'
    upstreams are summed first), so memory stays at one chunk whatever the image size.
    """

    @staticmethod
    def forward(ctx, captured, variance, rows, log_prior, bins, value_range, kernel):
        transposed = likelihood_counts(captured, variance, rows, log_prior, bins, value_range, kernel)
        ctx.save_for_backward(captured, variance, rows, log_prior)
        ctx.options = (bins, value_range, kernel)
        return transposed

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_transposed):
        captured, variance, rows, log_prior = ctx.saved_tensors
        bins, value_range, kernel = ctx.options
        want_captured, want_variance = ctx.needs_input_grad[:2]
        if not (want_captured or want_variance):
            return (None,) * 7
        mass = kernel == "mass" and log_prior is None
        # The mass weights' VJP needs upstream_k - upstream_k+1 per interior edge: differenced once per histogram row
        # here, not once per pixel.
        table = grad_transposed[:, :-1] - grad_transposed[:, 1:] if mass else grad_transposed.clone()
        table[-1] = 0
        floor = min_variance(bins, value_range)
        grad_captured = torch.empty(captured.shape, dtype=captured.dtype, device=captured.device)
        grad_variance = torch.empty(variance.shape, dtype=variance.dtype, device=variance.device)
        batch, pixels = captured.shape
        for part in _chunks(batch, pixels, bins, captured.device):
            upstream = table.index_select(0, rows[0, :, part].reshape(-1))
            for candidate_rows in rows[1:]:
                upstream += table.index_select(0, candidate_rows[:, part].reshape(-1))
            upstream = upstream.view(batch, -1, table.shape[-1])
            if mass:
                part_variance = variance[:, part]
                grad_captured[:, part], part_grad = mass_weights_vjp(
                    captured[:, part], part_variance.clamp_min(floor), upstream, bins, value_range
                )
                grad_variance[:, part] = part_grad.masked_fill_(part_variance < floor, 0.0)
            else:
                grad_captured[:, part], grad_variance[:, part] = likelihood_weights_vjp(
                    captured[:, part], variance[:, part], upstream, bins, value_range, kernel, log_prior
                )
        return (
            grad_captured if want_captured else None,
            grad_variance if want_variance else None,
            None,
            None,
            None,
            None,
            None,
        )
