"""Fixtures shared by the tests: dtypes and devices with their tolerances, seeded generators, real imagery."""

from __future__ import annotations

import numpy as np
import pytest
import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
TOLERANCES = {torch.float32: {"rtol": 1e-4, "atol": 1e-5}, torch.float64: {"rtol": 1e-9, "atol": 1e-10}}


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    return request.param


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)


@pytest.fixture
def tolerance(dtype) -> dict[str, float]:
    return TOLERANCES[dtype]


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(1234)


@pytest.fixture(scope="session")
def camera_image() -> np.ndarray:
    """scikit-image's bundled ``camera()`` (CC0), 512 x 512 uint8."""
    from skimage import data

    return data.camera()
