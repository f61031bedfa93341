"""A cheap surface's best peaks rescored exactly: the surfaces and searches that score few placements exactly.

The mixture score's surface and the two-stage search rank the placements by a cheap full surface, then score the
neighbourhoods of its best peaks with the exact score, doubling the peaks while the cheap ranking is not trusted.
"""

from __future__ import annotations

import torch
from torch import Tensor


def local_maxima(surface: Tensor) -> Tensor:
    """Flat indices of the finite maxima of their 3 x 3 (x 3) neighbourhood in ``surface``, best first (ties in order).

    ``surface`` is ``(rows, cols)`` or ``(yaws, rows, cols)``; a plateau's cells all count.

    Example:
        >>> surface = torch.tensor([[0.0, 5.0, 0.0, 0.0], [0.0, 0.0, 0.0, 3.0], [-torch.inf, 1.0, 0.0, 0.0]])
        >>> local_maxima(surface).tolist()  # 5 at (0, 1), 3 at (1, 3), 1 at (2, 1): two rows below the 5
        [1, 7, 9]
    """
    pooled = surface
    for axis in range(surface.ndim):  # separable 3 x 3 (x 3) maximum: max_pool3d is slow on the CPU
        padded = torch.nn.functional.pad(pooled.movedim(axis, -1), (1, 1), value=-torch.inf)
        pooled = torch.maximum(torch.maximum(padded[..., :-2], padded[..., 1:-1]), padded[..., 2:]).movedim(-1, axis)
    peaks = ((surface >= pooled) & torch.isfinite(surface)).flatten().nonzero()[:, 0]
    return peaks[surface.flatten()[peaks].argsort(descending=True, stable=True)]


def rescore_peaks(cheap: Tensor, exact, candidates: int, max_candidates: int, *, complete_best: bool = False) -> Tensor:
    """Exact scores around the best peaks of ``cheap`` (``(rows, cols)`` or ``(yaws, rows, cols)``), ``-inf`` elsewhere.

    ``exact`` maps placements ``(P, cheap.ndim)`` (indices) to scores ``(P,)``. Peaks are the finite maxima of their
    3 x 3 (x 3) neighbourhood, ranked by cheap score; each rescored placement belongs to the best-ranked peak it
    neighbours. The number of peaks doubles while the exact best belongs to a peak in the lower half of those rescored
    (up to ``max_candidates`` or every peak). With ``complete_best`` the exact best's own neighbourhood is then
    rescored too (and again while the best moves), for the sub-cell fit around it.
    """
    shape, device = cheap.shape, cheap.device
    peaks = local_maxima(cheap)
    limit = min(max_candidates, peaks.numel())
    offsets = torch.cartesian_prod(*[torch.arange(-1, 2, device=device)] * cheap.ndim).reshape(-1, cheap.ndim)
    sizes = torch.tensor(shape, device=device)
    strides = torch.tensor(torch.empty(shape, device="meta").stride(), device=device)
    owner = torch.full((cheap.numel(),), limit, dtype=torch.long, device=device)
    score = torch.full((cheap.numel(),), -torch.inf, dtype=cheap.dtype, device=device)
    rescored = torch.zeros(cheap.numel(), dtype=torch.bool, device=device)

    def unravel(flat: Tensor) -> Tensor:
        return torch.stack([flat // stride % size for stride, size in zip(strides, sizes, strict=True)], -1)

    def neighbours(flat: Tensor) -> tuple[Tensor, Tensor]:
        """Flat indices of the in-range neighbours of ``flat`` ``(n,)`` and whose neighbour each is."""
        around = unravel(flat).unsqueeze(1) + offsets
        inside = ((around >= 0) & (around < sizes)).all(-1)
        source = torch.arange(flat.numel(), device=device).unsqueeze(1).expand_as(inside)
        return (around[inside] * strides).sum(-1), source[inside]

    def rescore(flat: Tensor) -> None:
        score[flat] = exact(unravel(flat))
        rescored[flat] = True

    if limit == 0:
        return score.view(shape)
    done, count = 0, min(candidates, limit)
    while True:
        around, source = neighbours(peaks[done:count])
        owner.scatter_reduce_(0, around, source + done, "amin")
        rescore(((owner < count) & ~rescored).nonzero()[:, 0])
        best = int(score.argmax())
        if 2 * int(owner[best]) < count or count >= limit:
            break
        done, count = count, min(2 * count, limit)
    while complete_best:
        around = neighbours(score.argmax().reshape(1))[0]
        missing = around[~rescored[around]]
        if missing.numel() == 0:
            break
        rescore(missing)
    return score.view(shape)
