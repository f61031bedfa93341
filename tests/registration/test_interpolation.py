"""The map between its cells: the cubic B-spline and bilinear samples against scipy, their gradients, filled holes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from enmi_torch.registration.interpolation import MapSampler, bspline_coefficients, fill_unobserved

ORDERS = {"bspline": 3, "bilinear": 1}


def _maps(generator, dtype, batch=2, shape=(9, 13)):  # non-square: a swapped axis fails
    return torch.rand(batch, 1, *shape, generator=generator, dtype=torch.float64).to(dtype) * 200


def _positions(generator, dtype, batch=2, shape=(9, 13)):
    x = torch.rand(batch, 5, 7, generator=generator, dtype=torch.float64) * (shape[1] - 1)
    y = torch.rand(batch, 5, 7, generator=generator, dtype=torch.float64) * (shape[0] - 1)
    positions = torch.stack([x, y], -1)
    positions[0, 0, 0] = torch.tensor([shape[1] - 1.0, shape[0] - 1.0])  # the last cell itself
    positions[0, 0, 1] = torch.tensor([0.0, 0.0])
    return positions.to(dtype)


@pytest.mark.parametrize("interpolation", ["bspline", "bilinear"])
def test_samples_are_scipys_spline_of_the_same_order_mirrored_at_the_border(generator, dtype, interpolation):
    maps, positions = _maps(generator, dtype), _positions(generator, dtype)
    values, _ = MapSampler(maps, interpolation).sample(positions)
    assert values.dtype == dtype and values.shape == (2, 5, 7)
    for sample in range(2):
        at = [
            positions[sample, ..., 1].double().flatten().numpy(),
            positions[sample, ..., 0].double().flatten().numpy(),
        ]
        expected = ndimage.map_coordinates(
            maps[sample, 0].double().numpy(), at, order=ORDERS[interpolation], mode="mirror"
        )
        tolerance = 1e-9 if dtype == torch.float64 else 2e-3
        np.testing.assert_allclose(values[sample].double().flatten().numpy(), expected, rtol=0, atol=tolerance)


def test_the_spline_interpolates_the_cells_and_its_coefficients_are_scipys(generator):
    maps = _maps(generator, torch.float64)
    rows, cols = torch.meshgrid(torch.arange(9.0), torch.arange(13.0), indexing="ij")
    on_cells = torch.stack([cols, rows], -1).double().expand(2, 9, 13, 2)
    values, _ = MapSampler(maps, "bspline").sample(on_cells)
    torch.testing.assert_close(values, maps[:, 0], rtol=0, atol=1e-10)
    expected = ndimage.spline_filter(maps[1, 0].numpy(), order=3, mode="mirror")
    np.testing.assert_allclose(bspline_coefficients(maps)[1, 0].numpy(), expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize("interpolation", ["bspline", "bilinear"])
def test_the_gradient_is_the_derivative_of_the_samples(generator, interpolation):
    maps = _maps(generator, torch.float64)
    positions = _positions(generator, torch.float64)[:, 1:]  # off the cells' borders: one piece each
    sampler = MapSampler(maps, interpolation)
    _, slopes = sampler.sample(positions, gradient=True)
    moved = positions.clone().requires_grad_(True)
    (autograd,) = torch.autograd.grad(sampler.sample(moved)[0].sum(), moved)
    torch.testing.assert_close(slopes, autograd, rtol=0, atol=1e-9)
    step = 1e-6
    for axis in range(2):
        offset = torch.zeros_like(positions)
        offset[..., axis] = step
        numeric = (sampler.sample(positions + offset)[0] - sampler.sample(positions - offset)[0]) / (2 * step)
        torch.testing.assert_close(slopes[..., axis], numeric, rtol=0, atol=1e-5)


def test_one_map_per_image_is_read_by_the_images_row_and_off_the_map_is_zero(generator):
    maps = _maps(generator, torch.float64, batch=3)
    positions = _positions(generator, torch.float64, batch=3)
    sampler = MapSampler(maps, "bspline")
    every, _ = sampler.sample(positions)
    some, _ = sampler.sample(positions[[2, 0]], maps=torch.tensor([2, 0]))
    torch.testing.assert_close(some, every[[2, 0]], rtol=0, atol=0)
    alone, _ = MapSampler(maps[2:], "bspline").sample(positions[2:])
    torch.testing.assert_close(alone, every[2:], rtol=0, atol=1e-12)
    outside = torch.tensor([[[[-0.5, 3.0], [12.5, 3.0], [4.0, 8.01], [4.0, -3.0], [1e6, -1e6]]]], dtype=torch.float64)
    values, slopes = MapSampler(maps[:1], "bspline").sample(outside, gradient=True)
    assert values.abs().max() == 0 and slopes.abs().max() == 0


def test_an_unobserved_cell_takes_the_mean_of_the_observed_cells_nearest_it():
    reference = torch.arange(30.0, dtype=torch.float64).reshape(1, 1, 5, 6)
    observed = torch.ones_like(reference, dtype=torch.bool)
    observed[..., 2, 3] = False  # 8 observed neighbours
    observed[..., 0:5, 0] = False  # a whole column: the corner cells' nearest observed cells are the next column's
    filled = fill_unobserved(reference, observed)
    assert bool((filled[observed] == reference[observed]).all())
    assert float(filled[0, 0, 2, 3]) == pytest.approx(
        float(reference[0, 0, 1:4, 2:5].sum() - reference[0, 0, 2, 3]) / 8
    )
    assert float(filled[0, 0, 0, 0]) == pytest.approx(float(reference[0, 0, 0:2, 1].mean()))
    assert float(filled[0, 0, 2, 0]) == pytest.approx(float(reference[0, 0, 1:4, 1].mean()))
    isolated = torch.zeros(1, 1, 7, 7, dtype=torch.bool)
    isolated[..., 6, 6] = True  # one observed cell, far from most: the neighbourhood grows until it reaches it
    grown = fill_unobserved(torch.full((1, 1, 7, 7), 5.0, dtype=torch.float64), isolated)
    torch.testing.assert_close(grown, torch.full_like(grown, 5.0), rtol=1e-12, atol=0)
