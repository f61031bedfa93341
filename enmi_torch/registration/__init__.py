"""Registration: the continuous pose of captured images in a map, by Gauss-Newton through a score.

:mod:`~enmi_torch.registration.refine` holds :func:`register` (refine from a pose, e.g. :func:`~enmi_torch.localize`'s)
and :func:`registration_score` (the score it maximises, differentiable in the pose); its stages are in
:mod:`~enmi_torch.registration.stage`. :mod:`~enmi_torch.registration.warp` holds :func:`warp_reference` (the map under
the captured image at a pose), :mod:`~enmi_torch.registration.interpolation` the map between its cells (a cubic
B-spline, or bilinear) and :mod:`~enmi_torch.registration.response_fit` the score's least-squares fit.
"""

from enmi_torch.registration.refine import Registration, register, registration_score
from enmi_torch.registration.warp import warp_reference

__all__ = ["Registration", "register", "registration_score", "warp_reference"]
