"""Every placement at once: the machinery the score surfaces share, below the scores.

Data flow, each module importing only the ones before it: :mod:`~enmi_torch.placement.inputs` (checked inputs and the
:class:`Surface` result) → :mod:`~enmi_torch.placement.fft` (FFT correlation of captured planes with reference planes
at the placements only, box sums) → :mod:`~enmi_torch.placement.planes` (the reference's bin planes, moment planes)
→ :mod:`~enmi_torch.placement.information` (the NMI surface of joint histograms that ENMI and NMI share);
:mod:`~enmi_torch.placement.peaks` (a cheap surface's peaks rescored exactly) and
:mod:`~enmi_torch.placement.direct` (every placement scored on its own: the reference loop). The scores
(:mod:`enmi_torch.scores`) build their surfaces from these pieces; nothing here knows a score by name.
"""

from enmi_torch.placement.fft import fft_size
from enmi_torch.placement.inputs import Surface

__all__ = ["Surface", "fft_size"]
