"""Registration: the continuous pose of captured images in a map, by Gauss-Newton through a score.

:mod:`~enmi_torch.registration.refine` holds :func:`register` (refine from a pose, e.g. :func:`~enmi_torch.localize`'s
peak), :func:`registration_score` (the score it maximises, differentiable in the pose) and :func:`warp_reference` (the
map under the captured image at a pose).
"""

from enmi_torch.registration.refine import Registration, register, registration_score, warp_reference

__all__ = ["Registration", "register", "registration_score", "warp_reference"]
