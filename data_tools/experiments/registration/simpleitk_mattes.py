"""SimpleITK's Mattes mutual-information registration, the outside reference of the registration benchmarks.

``mattes_registration`` registers each captured image in its map, one at a time, from a start pose; it is what
``bench_register`` times and what ``subcell`` compares ``register`` with. SimpleITK is the ``bench`` extra.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch


def mattes_registration(maps: Sequence[torch.Tensor], captured: torch.Tensor, start: torch.Tensor, rigid: bool = True):
    """``(N, 3)`` float64 poses ``(x, y, yaw)`` of ``captured`` ``(N, 1, h, w)`` in ``maps[i]`` ``(H, W)``.

    From ``start`` ``(N, 3)`` (the captured image's centre on the map, yaw in degrees): rigid (``Euler2DTransform``
    about the image's centre) or, with ``rigid=False``, a translation from the start's whole cells. Mattes MI with 32
    bins over every pixel, linear interpolation, regular-step gradient descent over two levels (shrink 2, 1).
    """
    import SimpleITK as sitk

    height, width = captured.shape[-2:]
    middle = ((width - 1) / 2, (height - 1) / 2)
    poses = []
    for index, reference in enumerate(maps):
        fixed = sitk.GetImageFromArray(captured[index, 0].numpy().astype(np.float32))
        moving = sitk.GetImageFromArray(reference.numpy().astype(np.float32))
        x, y, yaw = start[index].tolist()
        if rigid:
            transform = sitk.Euler2DTransform()  # fixed (captured) pixel -> moving (map) point
            transform.SetCenter(middle)
            transform.SetAngle(math.radians(yaw))
            transform.SetTranslation((x - width // 2, y - height // 2))
        else:
            transform = sitk.TranslationTransform(2, (round(x) - width // 2, round(y) - height // 2))
        method = sitk.ImageRegistrationMethod()
        method.SetMetricAsMattesMutualInformation(numberOfHistogramBins=32)
        method.SetMetricSamplingStrategy(method.NONE)
        method.SetInterpolator(sitk.sitkLinear)
        method.SetOptimizerAsRegularStepGradientDescent(
            learningRate=1.0, minStep=1e-4, numberOfIterations=200, gradientMagnitudeTolerance=1e-8
        )
        method.SetOptimizerScalesFromPhysicalShift()
        method.SetShrinkFactorsPerLevel([2, 1])
        method.SetSmoothingSigmasPerLevel([1, 0])
        method.SetInitialTransform(transform, inPlace=True)
        method.Execute(fixed, moving)
        if rigid:
            angle = math.degrees(transform.GetAngle())
            shift_x, shift_y = transform.GetTranslation()
        else:
            angle = 0.0
            shift_x, shift_y = transform.GetOffset()
        poses.append([shift_x + width // 2, shift_y + height // 2, angle])
    return torch.tensor(poses, dtype=torch.float64).reshape(-1, 3)
