"""What the model page's tests share: the page's equation labels, the ``guards`` tag, scenes, the page's bins.

Each test of ``tests/docs/test_model_page*.py`` names the equations of ``docs/model.md`` it checks with
``@guards("eq-...")``; ``test_model_page.py`` checks that every labelled equation on the page has such a test. The
page's side of each test is a direct float64 evaluation of the formula as the page writes it (NumPy, SciPy, loops),
never the library's code.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "model.md"
# A displayed equation: "$$", its lines, "$$ (label)".
DISPLAY = re.compile(r"^\$\$\n(.*?)\n\$\$(?: \((?P<label>[\w-]+)\))?$", re.MULTILINE | re.DOTALL)


def page_equations() -> list[tuple[str | None, str]]:
    """``(label or None, LaTeX)`` of every displayed equation of the model page, in order."""
    text = re.sub(r"^```.*?^```", "", PAGE.read_text(), flags=re.MULTILINE | re.DOTALL)
    return [(match.group("label"), match.group(1)) for match in DISPLAY.finditer(text)]


def guards(*labels: str):
    """Tag a test with the page's equation labels it checks (read back by ``test_model_page.py``)."""

    def tag(test):
        test.guards = labels
        return test

    return tag


def image(values: np.ndarray, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """A ``(H, W)`` array as a ``(1, 1, H, W)`` tensor."""
    return torch.tensor(values, dtype=dtype)[None, None]


def hard_bin(values: np.ndarray, bins: int, value_range: tuple[float, float]) -> np.ndarray:
    """The page's hard bin, eq-hard-bin: ``min(K - 1, max(0, floor((x - l) / Delta)))``."""
    low, high = value_range
    width = (high - low) / bins
    return np.minimum(bins - 1, np.maximum(0, np.floor((values - low) / width))).astype(int)


class Scene(NamedTuple):
    """A captured image over its reference: values, reference, noise variance and valid mask, ``(H, W)`` float64."""

    captured: np.ndarray
    reference: np.ndarray
    variance: np.ndarray
    valid: np.ndarray


def scene(
    shape: tuple[int, int] = (9, 14),
    *,
    seed: int = 3,
    response: str = "nonmonotonic",
    misfit: float = 0.0,
    invalid: int = 0,
) -> Scene:
    """A non-square scene that tells conventions apart: per-pixel variances from 4 to 1800, unequal along each axis.

    ``response``: ``"nonmonotonic"`` (``255 |2 r / 255 - 1|^0.8``, a V) or ``"increasing"`` (``1.2 r - 20`` plus a
    ripple); ``misfit``: the standard deviation of an extra Gaussian misfit; ``invalid``: pixels marked invalid (their
    captured value NaN).
    """
    generator = np.random.default_rng(seed)
    height, width = shape
    reference = generator.uniform(5.0, 251.0, shape)
    if response == "nonmonotonic":
        mean = 255 * np.abs(2 * reference / 255 - 1) ** 0.8
    else:
        mean = 1.2 * reference - 20 + 15 * np.sin(reference / 17)
    variance = np.outer(np.linspace(4.0, 900.0, height), np.linspace(1.0, 2.0, width))
    captured = mean + np.sqrt(variance) * generator.standard_normal(shape) + misfit * generator.standard_normal(shape)
    valid = np.ones(shape, dtype=bool)
    if invalid:
        valid.flat[generator.choice(height * width, invalid, replace=False)] = False
        captured = np.where(valid, captured, np.nan)
    return Scene(captured, reference, variance, valid)
