"""ECR's correlated misfit (``misfit="correlated"``): the pixels per independent misfit (:func:`misfit_extent`) against
a direct loop and closed forms, and the estimate, surfaces and search that use it."""

import math

import pytest
import torch

from enmi_torch import ECR, localize
from enmi_torch.binning import hard_bin_index
from enmi_torch.functional import ecr
from enmi_torch.scores.ecr import ecr_model_variance, ecr_surface_model_variance
from enmi_torch.scores.ecr_model_variance import MISFIT_REACH, misfit_extent

RANGE = (0.0, 256.0)


def _direct_extent(residual, valid, tau2) -> float:
    """:func:`misfit_extent` of one image by loops over the lags and the pixel pairs."""
    height, width = residual.shape
    reach = max(1, round(MISFIT_REACH * min(height, width)))
    values = [[float(residual[y, x]) for x in range(width)] for y in range(height)]
    inside = [[bool(valid[y, x]) for x in range(width)] for y in range(height)]
    count = sum(map(sum, inside))
    mean = sum(values[y][x] for y in range(height) for x in range(width) if inside[y][x]) / count
    total = 0.0
    for dy in range(-min(reach, height - 1), min(reach, height - 1) + 1):
        for dx in range(-min(reach, width - 1), min(reach, width - 1) + 1):
            if dy == 0 and dx == 0:
                continue
            products, pairs = 0.0, 0
            for y in range(max(0, -dy), min(height, height - dy)):
                for x in range(max(0, -dx), min(width, width - dx)):
                    if inside[y][x] and inside[y + dy][x + dx]:
                        products += (values[y][x] - mean) * (values[y + dy][x + dx] - mean)
                        pairs += 1
            if pairs:
                taper = (1 - abs(dy) / (reach + 1)) * (1 - abs(dx) / (reach + 1))
                total += taper * products / pairs
    return min(max(1 + total / tau2, 1.0), count)


def _block_field(generator, height, width, block_y, block_x, dtype=torch.float64):
    """A field constant over ``block_y x block_x`` blocks, the blocks independent standard normals."""
    blocks = torch.randn(height // block_y + 1, width // block_x + 1, generator=generator, dtype=dtype)
    return blocks.repeat_interleave(block_y, 0).repeat_interleave(block_x, 1)[:height, :width]


def _share(block: int, reach: int) -> float:
    """The tapered lag sum of a block-constant field's correlation along one axis (blocks at random offsets)."""
    return 1 + 2 * sum((1 - d / block) * (1 - d / (reach + 1)) for d in range(1, block))


def test_the_extent_is_the_tapered_lag_sum_of_a_direct_loop(dtype, generator):
    # Non-square (the negative lags wrap by each axis's own padded size), masked (NaN under the mask), correlated
    # along the columns only.
    residual = _block_field(generator, 17, 41, 1, 5) + 0.3 * torch.randn(
        17, 41, generator=generator, dtype=torch.float64
    )
    valid = torch.rand(17, 41, generator=generator) > 0.2
    residual = torch.where(valid, residual, math.nan)
    tau2 = torch.tensor([0.8], dtype=torch.float64)
    found = misfit_extent(residual[None].to(dtype), valid[None], tau2.to(dtype))
    expected = _direct_extent(residual, valid, 0.8)
    assert expected > 2  # the correlation along the columns counts
    tolerance = 1e-9 if dtype == torch.float64 else 1e-4
    assert float(found[0]) == pytest.approx(expected, rel=tolerance)
    assert found.dtype == dtype


def test_a_single_row_image_sums_its_lags_along_the_row_only(generator):
    # One row: no row lags exist, the reach along the columns is the smallest side's (at least one lag).
    residual = _block_field(generator, 1, 200, 1, 3)
    valid = torch.ones(1, 200, dtype=torch.bool)
    found = misfit_extent(residual[None], valid[None], torch.ones(1, dtype=torch.float64))
    assert float(found[0]) == pytest.approx(_direct_extent(residual, valid, 1.0), rel=1e-9)
    assert float(found[0]) > 1.2  # the lag-1 neighbours along the row count


@pytest.mark.parametrize(("block_y", "block_x"), [(1, 1), (4, 4), (2, 6)])
def test_a_block_constant_misfit_gives_the_closed_form_share_of_its_block(generator, block_y, block_x):
    height, width = 120, 96  # the reach follows the smaller side: round(96 / 8) = 12
    reach = round(MISFIT_REACH * width)
    fields = torch.stack([_block_field(generator, height, width, block_y, block_x) for _ in range(24)])
    noise = torch.randn(fields.shape, generator=generator, dtype=torch.float64)  # white: lag 0 only
    valid = torch.ones(fields.shape, dtype=torch.bool)
    extent = misfit_extent(fields + 0.5 * noise, valid, torch.ones(24, dtype=torch.float64))
    expected = _share(block_y, reach) * _share(block_x, reach)
    assert float(extent.mean()) == pytest.approx(expected, rel=0.06, abs=0.15)


def test_the_extent_is_at_least_one_and_at_most_the_valid_pixels():
    checkerboard = (torch.arange(16)[:, None] + torch.arange(16)).remainder(2).double()[None] * 2 - 1
    ramp = torch.arange(16, dtype=torch.float64).expand(1, 16, 16)
    valid = torch.ones(1, 16, 16, dtype=torch.bool)
    valid[0, 0, 0] = False
    # Neighbours of opposite sign sum to a negative lag sum: floored at one pixel.
    assert float(misfit_extent(checkerboard, valid, torch.ones(1).double())[0]) == 1.0
    # A smooth misfit of tiny variance: capped at the 255 valid pixels.
    assert float(misfit_extent(ramp, valid, torch.tensor([1e-9]).double())[0]) == 255.0


def _images(generator, misfit_block, *, tau2=400.0, noise_variance=100.0, size=(48, 64)):
    """A map, a captured section of it at (5, 9) with a misfit of ``tau2`` over blocks and white noise."""
    height, width = size
    reference = torch.rand(1, 1, height + 12, width + 16, generator=generator, dtype=torch.float64) * 256
    section = reference[..., 5 : 5 + height, 9 : 9 + width]
    means = 40 + 120 * torch.sin(hard_bin_index(section, 32, RANGE).double() * 0.7)
    misfit = math.sqrt(tau2) * _block_field(generator, height, width, misfit_block, misfit_block)
    noise = math.sqrt(noise_variance) * torch.randn(1, 1, height, width, generator=generator, dtype=torch.float64)
    return means + misfit + noise, reference, section


def test_an_independent_misfit_keeps_the_estimate_and_a_blocky_one_multiplies_it(generator):
    for block, low, high in ((1, 0.9, 1.15), (4, 0.7 * 11.9, 1.3 * 11.9)):
        captured, _, section = _images(generator, block)
        independent = ecr_model_variance(captured, section, 100.0)
        correlated = ecr_model_variance(captured, section, 100.0, misfit="correlated")
        assert low < float(correlated[0] / independent[0]) < high, block
        assert 300 < float(independent[0]) < 500  # the per-pixel estimate is the misfit's variance either way


def test_ecr_with_a_correlated_misfit_is_ecr_with_its_model_variance(dtype, generator):
    captured, _, section = _images(generator, 4)
    mask = torch.rand(captured.shape, generator=generator) > 0.1
    captured, section = captured.to(dtype), section.to(dtype)
    tau2 = ecr_model_variance(captured, section, 100.0, misfit="correlated", valid_mask=mask)
    value = ecr(captured, section, 100.0, misfit="correlated", valid_mask=mask)
    delta2 = ECR(misfit="correlated").response_variance_of(captured, section, 100.0, valid_mask=mask)
    options = {"model_variance": float(tau2[0]), "response_variance": float(delta2[0]), "valid_mask": mask}
    fixed = ecr(captured, section, 100.0, **options)
    torch.testing.assert_close(value, fixed)
    assert float(tau2[0]) > 4 * float(ecr_model_variance(captured, section, 100.0, valid_mask=mask)[0])


def test_a_surface_reads_the_correlated_estimate_at_its_peak_and_the_search_agrees(generator):
    captured, reference, section = _images(generator, 4)
    score = ECR(misfit="correlated")
    tau2 = score.surface_model_variance(captured, reference, 100.0)
    torch.testing.assert_close(tau2, score.model_variance_of(captured, section, 100.0), rtol=1e-6, atol=0)
    assert float(tau2[0]) > 1000  # about 12 x the misfit's 400
    surface = score.surface(captured, reference, 100.0)
    delta2 = score.surface_response_variance(captured, reference, 100.0)
    fixed = ECR(model_variance=float(tau2[0]), response_variance=float(delta2[0])).surface(captured, reference, 100.0)
    torch.testing.assert_close(surface.score, fixed.score, rtol=1e-9, atol=1e-9)
    assert divmod(int(surface.score[0].argmax()), surface.score.shape[-1]) == (5, 9)
    options = {"score": score, "shifts": (6, 8), "around": (40, 30), "yaws": [0.0]}
    exhaustive = localize(captured, reference, 100.0, **options).surface
    staged = localize(captured, reference, 100.0, search="two_stage", **options).surface
    rescored = torch.isfinite(staged)
    torch.testing.assert_close(staged[rescored], exhaustive[rescored], rtol=1e-9, atol=1e-9)
    assert ecr_surface_model_variance(captured, reference, 100.0, misfit="correlated").shape == (1,)


def test_bad_misfits_are_refused():
    with pytest.raises(ValueError, match="misfit must be one of"):
        ECR(misfit="spatial")
    with pytest.raises(ValueError, match="misfit must be one of"):
        ecr(torch.ones(1, 4, 4), torch.ones(1, 4, 4), 1.0, misfit="blocks")
    flat = torch.rand(2, 16, generator=torch.Generator().manual_seed(0)) * 256
    with pytest.raises(ValueError, match=r"captured must have shape \(B, 1, H, W\) or \(B, H, W\), got the 2-D"):
        ecr(flat, flat, 1.0, misfit="correlated")  # flat samples are (B, 1, N): one row of pixels each


def test_the_quantisation_floor_stays_per_pixel_and_only_the_excess_is_multiplied(generator):
    # A smooth map seen through white noise: the residual within each bin is the map's own (correlated) variation, and
    # the estimate sits at the floor, bin_width^2 / 12; the correlated misfit leaves it there.
    rows = torch.linspace(0, 255, 48, dtype=torch.float64)[:, None]
    smooth = (rows + torch.linspace(0, 60, 64, dtype=torch.float64)).clamp(0, 255).expand(1, 1, 48, 64)
    captured = smooth + 2 * torch.randn(1, 1, 48, 64, generator=generator, dtype=torch.float64)
    floor = 256.0**2 / 16**2 / 12
    for misfit in ("independent", "correlated"):
        assert float(ecr_model_variance(captured, smooth, 100.0, bins=16, misfit=misfit)[0]) == floor
    # With a misfit beyond the floor, the correlated estimate is the floor plus the excess times the extent of the
    # residuals about the bin means weighted at the independent estimate.
    # The noise variance varies (tenfold down the rows), so weighted and plain bin means differ.
    captured, _, section = _images(generator, 4)
    variance = (10 ** torch.linspace(2, 3, 48, dtype=torch.float64))[:, None].expand(1, 1, 48, 64)
    tau2 = ecr_model_variance(captured, section, variance, bins=16)
    weight = (1 / (variance + tau2)).flatten()
    cells = hard_bin_index(section.flatten(), 16, RANGE)
    values = captured.flatten() - captured.mean()
    sums = torch.zeros(16, dtype=torch.float64).index_add(0, cells, weight * values)
    means = sums / torch.zeros(16, dtype=torch.float64).index_add(0, cells, weight).clamp_min(1e-300)
    residual = (values - means[cells]).view(1, 48, 64)
    extent = misfit_extent(residual, torch.ones(1, 48, 64, dtype=torch.bool), tau2)
    expected = floor + (tau2 - floor) * extent
    found = ecr_model_variance(captured, section, variance, bins=16, misfit="correlated")
    torch.testing.assert_close(found, expected, rtol=1e-9, atol=0)


def test_with_nothing_to_estimate_from_the_correlated_estimate_is_the_floor(generator):
    captured, _, section = _images(generator, 4)
    few = torch.zeros(captured.shape, dtype=torch.bool)
    few[..., 0, :3] = True  # fewer valid pixels than occupied bins
    for misfit in ("independent", "correlated"):
        found = ecr_model_variance(captured, section, 100.0, bins=256, valid_mask=few, misfit=misfit)
        assert float(found[0]) == 256.0**2 / 256**2 / 12
