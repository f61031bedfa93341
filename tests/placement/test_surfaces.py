import math

import numpy as np
import pytest
import torch
from skimage import data

from enmi_torch import ECR, ENMI, NCC, NMI
from enmi_torch.functional import ecr_surface, enmi, enmi_surface, gaussian_log_prior, ncc_surface, nmi, nmi_surface
from enmi_torch.placement import Surface, fft_size
from enmi_torch.placement import fft as placement_fft
from enmi_torch.scores import direct_surface

FAMILIES = {"ecr": ECR, "enmi": ENMI, "nmi": NMI, "ncc": NCC}


def _direct(local, window, variance=None, *, metric="enmi", captured_mask=None, reference_mask=None, **options):
    """direct_surface of the family ``metric`` with ``options``."""
    masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
    return direct_surface(FAMILIES[metric](**options), local, window, variance, **masks)


def _case(dtype, *, batch=2, local_shape=(9, 7), window_shape=(16, 15), seed=0):
    """Gravel local images (one cut from the window, noisy), per-pixel variances and masks with partial overlap."""
    generator = torch.Generator().manual_seed(seed)
    gravel = torch.from_numpy(data.gravel()).to(dtype)
    window = gravel[100 : 100 + window_shape[0], 200 : 200 + window_shape[1]].reshape(1, 1, *window_shape)
    height, width = local_shape
    local = torch.rand(batch, 1, height, width, generator=generator, dtype=dtype) * 256
    local[0] = window[..., 3 : 3 + height, 4 : 4 + width] + 6 * torch.randn(
        height, width, generator=generator, dtype=dtype
    )
    variance = torch.rand(batch, 1, height, width, generator=generator, dtype=dtype) * 60 + 2
    captured_mask = torch.rand(batch, 1, height, width, generator=generator) > 0.25
    reference_mask = torch.rand(1, 1, *window_shape, generator=generator) > 0.15
    # An unmapped band: the placements on the left overlap it partly, the first ones almost entirely.
    reference_mask[..., : width - 1] = False
    reference_mask[..., :2, width - 1] = False
    return local, window, variance, captured_mask, reference_mask


@pytest.mark.parametrize(
    ("metric", "options"),
    [
        ("enmi", {"kernel": "mass"}),
        ("enmi", {"kernel": "density"}),
        ("enmi", {"kernel": "truncated"}),
        ("enmi", {"kernel": "mass", "log_prior": "prior"}),
        ("nmi", {}),
        ("ncc", {}),
    ],
)
def test_fft_surface_equals_direct_loop_with_masks_and_partial_overlap(metric, options):
    local, window, variance, captured_mask, reference_mask = _case(torch.float64)
    options = dict(options)
    if options.get("log_prior") == "prior":
        options["log_prior"] = gaussian_log_prior(128.0, 40.0, 12, (0.0, 256.0), dtype=torch.float64)
    masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
    binned = {} if metric == "ncc" else {"bins": 12, "value_range": (0.0, 256.0)}
    if metric == "enmi":
        fast = enmi_surface(local, window, variance, **binned, **options, **masks)
    elif metric == "nmi":
        fast = nmi_surface(local, window, **binned, **masks)
    else:
        fast = ncc_surface(local, window, **masks)
    reference = _direct(
        local, window, variance if metric == "enmi" else None, metric=metric, **binned, **options, **masks
    )
    assert isinstance(fast, Surface)
    assert fast.score.shape == (2, 8, 9)
    assert fast.score.dtype == torch.float64
    # The window mask leaves some placements with partial and some with tiny overlap.
    assert reference.overlap.min() < 10 < reference.overlap.max()
    torch.testing.assert_close(fast.overlap, reference.overlap, rtol=0, atol=0)
    torch.testing.assert_close(fast.score, reference.score, rtol=0, atol=1e-9)


@pytest.mark.parametrize("metric", ["enmi", "nmi", "ncc"])
@pytest.mark.parametrize("masked", ["none", "local", "window", "both"])
def test_fft_surface_equals_direct_loop_for_each_mask_combination(metric, masked):
    # Masks that leave nothing out take other paths (constant marginals, box-summed counts) than partial ones.
    local, window, variance, captured_mask, reference_mask = _case(torch.float64)
    reference_mask[..., :, :3] = True  # leave a full-overlap placement or two even with the window mask
    masks = {
        "captured_mask": captured_mask if masked in ("local", "both") else None,
        "reference_mask": reference_mask if masked in ("window", "both") else None,
    }
    binned = {} if metric == "ncc" else {"bins": 12}
    if metric == "enmi":
        fast = enmi_surface(local, window, variance, **binned, **masks)
    elif metric == "nmi":
        fast = nmi_surface(local, window, **binned, **masks)
    else:
        fast = ncc_surface(local, window, **masks)
    reference = _direct(local, window, variance if metric == "enmi" else None, metric=metric, **binned, **masks)
    torch.testing.assert_close(fast.overlap, reference.overlap, rtol=0, atol=0)
    torch.testing.assert_close(fast.score, reference.score, rtol=0, atol=1e-9)
    if masked == "none":
        assert bool((fast.overlap == 9 * 7).all())


@pytest.mark.parametrize("masked", [False, True])
def test_blocks_of_reference_planes_give_the_one_block_surface(monkeypatch, masked):
    # Tiny blocks: several per captured plane, the last one shorter, the mask plane alone in a block or with bins.
    local, window, variance, captured_mask, reference_mask = _case(torch.float64)
    masks = {"captured_mask": captured_mask, "reference_mask": reference_mask} if masked else {}
    whole = enmi_surface(local, window, variance, bins=12, **masks)
    half_spectrum = fft_size(16) * (fft_size(15) // 2 + 1)
    for planes_per_block in (1, 2, 5):
        monkeypatch.setattr(placement_fft, "_BLOCK_ELEMENTS", planes_per_block * half_spectrum)
        blocked = enmi_surface(local, window, variance, bins=12, **masks)
        torch.testing.assert_close(blocked.score, whole.score, rtol=0, atol=1e-12)
        torch.testing.assert_close(blocked.overlap, whole.overlap, rtol=0, atol=0)
    reference = _direct(local, window, variance, bins=12, **masks)
    torch.testing.assert_close(blocked.score, reference.score, rtol=0, atol=1e-9)


def test_surface_entries_equal_the_public_scores_at_each_placement():
    local, window, variance, captured_mask, reference_mask = _case(torch.float64, batch=1)
    fast_enmi = enmi_surface(
        local, window, variance, bins=16, captured_mask=captured_mask, reference_mask=reference_mask
    )
    fast_nmi = nmi_surface(
        local, window, bins=16, captured_mask=captured_mask, reference_mask=reference_mask, kernel="hard"
    )
    for row, col in [(0, 8), (4, 6), (7, 8), (3, 4)]:
        section = window[..., row : row + 9, col : col + 7]
        valid = captured_mask & reference_mask[..., row : row + 9, col : col + 7]
        expected = enmi(local, section, variance, bins=16, valid_mask=valid)
        torch.testing.assert_close(fast_enmi.score[:, row, col], expected, rtol=0, atol=1e-9)
        torch.testing.assert_close(
            fast_nmi.score[:, row, col], nmi(local, section, bins=16, valid_mask=valid, kernel="hard")
        )


def test_ncc_entries_equal_numpy_corrcoef():
    local, window, _, captured_mask, reference_mask = _case(torch.float64, batch=1)
    surface = ncc_surface(local, window, captured_mask=captured_mask, reference_mask=reference_mask)
    for row, col in [(0, 8), (5, 7), (7, 6)]:
        valid = (captured_mask & reference_mask[..., row : row + 9, col : col + 7]).numpy().ravel()
        captured = local.numpy().ravel()[valid]
        section = window[..., row : row + 9, col : col + 7].numpy().ravel()[valid]
        assert surface.score[0, row, col].item() == pytest.approx(np.corrcoef(captured, section)[0, 1], abs=1e-9)


@pytest.mark.parametrize("metric", ["enmi", "nmi", "ncc"])
def test_float32_surface_is_close_to_the_float64_reference(metric):
    local, window, variance, captured_mask, reference_mask = _case(
        torch.float64, local_shape=(24, 20), window_shape=(34, 33)
    )
    masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
    binned = {} if metric == "ncc" else {"bins": 16}
    reference = _direct(local, window, variance if metric == "enmi" else None, metric=metric, **binned, **masks)
    single = {"captured": local.float(), "reference": window.float(), **masks}
    if metric == "enmi":
        fast = enmi_surface(variance=variance.float(), bins=16, **single)
    elif metric == "nmi":
        fast = nmi_surface(bins=16, **single)
    else:
        fast = ncc_surface(**single)
    assert fast.score.dtype == torch.float32
    torch.testing.assert_close(fast.overlap.double(), reference.overlap, rtol=0, atol=0)
    torch.testing.assert_close(fast.score.double(), reference.score, rtol=0, atol=2e-5)


def test_batched_surface_equals_per_sample_calls_and_per_sample_windows():
    local, window, variance, captured_mask, _ = _case(torch.float64, batch=3)
    windows = torch.cat([window, window.flip(-1), window.flip(-2)])
    batched = enmi_surface(local, windows, variance, bins=8, captured_mask=captured_mask)
    for sample in range(3):
        single = enmi_surface(
            local[sample : sample + 1],
            windows[sample : sample + 1],
            variance[sample : sample + 1],
            bins=8,
            captured_mask=captured_mask[sample : sample + 1],
        )
        torch.testing.assert_close(batched.score[sample], single.score[0], rtol=0, atol=1e-12)
    shared = enmi_surface(local, window, variance, bins=8, captured_mask=captured_mask)
    torch.testing.assert_close(shared.score[0], batched.score[0], rtol=0, atol=1e-12)


def test_enmi_surface_tends_to_the_nmi_surface_as_the_variance_vanishes():
    local, window, _, captured_mask, reference_mask = _case(torch.float64)
    # Half-integer values sit 0.5 grey levels from every bin edge: far out of reach of a vanishing variance.
    local = local.floor() + 0.5
    masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
    sharp = enmi_surface(local, window, 1e-8, bins=16, **masks)
    hard = nmi_surface(local, window, bins=16, kernel="hard", **masks)
    torch.testing.assert_close(sharp.score, hard.score, rtol=0, atol=1e-9)


def test_placement_without_overlap_scores_as_independent_images():
    local, window, variance, _, _ = _case(torch.float64, batch=1)
    reference_mask = torch.ones(1, 1, 16, 15, dtype=torch.bool)
    reference_mask[..., :, :7] = False
    for surface, empty_score in [
        (enmi_surface(local, window, variance, bins=8, reference_mask=reference_mask), 1.0),
        (nmi_surface(local, window, bins=8, reference_mask=reference_mask, kernel="hard"), 1.0),
        (ncc_surface(local, window, reference_mask=reference_mask), 0.0),
    ]:
        assert surface.overlap[0, :, 0].eq(0).all()
        assert surface.score[0, :, 0].eq(empty_score).all()
        assert surface.overlap[0, :, 1].gt(0).all()


def test_peak_is_at_the_cut_position():
    local, window, variance, _, _ = _case(torch.float32, batch=1, local_shape=(20, 20), window_shape=(40, 40))
    for surface in [
        enmi_surface(local, window, variance),
        nmi_surface(local, window, kernel="hard"),
        ncc_surface(local, window),
    ]:
        assert divmod(int(surface.score[0].flatten().argmax()), 21) == (3, 4)


def test_surfaces_of_nan_pixels_outside_the_masks_are_finite():
    local, window, variance, captured_mask, reference_mask = _case(torch.float64, batch=1)
    local = local.masked_fill(~captured_mask, math.nan)
    window = window.masked_fill(~reference_mask, math.nan)
    masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
    for surface in [
        enmi_surface(local, window, variance, **masks),
        nmi_surface(local, window, **masks),
        ncc_surface(local, window, **masks),
    ]:
        assert torch.isfinite(surface.score).all()


def test_fft_size_is_the_smallest_five_smooth_length():
    def smooth(number):
        for prime in (2, 3, 5):
            while number % prime == 0:
                number //= prime
        return number == 1

    for length in range(1, 400):
        size = fft_size(length)
        assert size >= length and smooth(size)
        assert not any(smooth(candidate) for candidate in range(length, size))


def test_surface_runs_on_the_device(device):
    local, window, variance, captured_mask, reference_mask = _case(torch.float64)
    expected = enmi_surface(local, window, variance, captured_mask=captured_mask, reference_mask=reference_mask)
    moved = enmi_surface(
        local.to(device),
        window.to(device),
        variance.to(device),
        captured_mask=captured_mask.to(device),
        reference_mask=reference_mask.to(device),
    )
    torch.testing.assert_close(moved.score.cpu(), expected.score)


def _invalid_cases():
    local, window, variance, captured_mask, reference_mask = _case(torch.float64)
    empty_local = torch.zeros_like(captured_mask)
    empty_local[0] = True
    return [
        ({"captured": local.long()}, TypeError, "captured must be a floating-point tensor"),
        ({"captured": local[:, 0]}, ValueError, r"captured must have shape \(B, 1, h, w\)"),
        ({"reference": window[..., :8, :]}, ValueError, "reference must be at least as large as captured"),
        ({"reference": torch.cat([window] * 3)}, ValueError, r"reference must have shape \(1, 1, Hw, Ww\) or \(2, 1"),
        ({"variance": variance[..., :5]}, ValueError, "variance must have the spatial shape"),
        ({"variance": -variance}, ValueError, "variance must be finite and > 0"),
        ({"variance": None}, ValueError, "variance must be a number or a tensor"),
        ({"captured_mask": captured_mask.float()}, TypeError, "captured_mask must be a bool tensor"),
        ({"captured_mask": empty_local}, ValueError, r"captured_mask selects no pixel in sample\(s\) \[1\]"),
        ({"reference_mask": torch.zeros_like(reference_mask)}, ValueError, "reference_mask selects no pixel"),
        ({"reference_mask": reference_mask[..., :3]}, ValueError, "reference_mask must have the spatial shape"),
        ({"captured": local.masked_fill(captured_mask, math.nan)}, ValueError, "captured must be finite"),
        ({"bins": 1}, ValueError, "bins must be an int >= 2"),
        ({"value_range": (5.0, 1.0)}, ValueError, "value_range must be finite with low < high"),
        ({"kernel": "gauss"}, ValueError, "kernel must be one of"),
        ({"log_prior": torch.zeros(3)}, ValueError, r"log_prior must have shape \(32,\)"),
    ], (local, window, variance, captured_mask, reference_mask)


@pytest.mark.parametrize("index", range(16))
def test_invalid_inputs_raise_clear_errors(index):
    cases, (local, window, variance, captured_mask, reference_mask) = _invalid_cases()
    change, error, message = cases[index]
    arguments = {"captured": local, "reference": window, "variance": variance, "captured_mask": captured_mask}
    arguments["reference_mask"] = reference_mask
    arguments.update(change)
    with pytest.raises(error, match=message):
        enmi_surface(**arguments)


def test_direct_surface_checks_its_score_and_variance():
    local, window, variance, _, _ = _case(torch.float64)
    with pytest.raises(ValueError, match=r"score must be a Score or one of \['ecr', 'enmi', 'mixture', 'ncc', 'nmi'\]"):
        direct_surface("mi", local, window, variance)
    with pytest.raises(ValueError, match="variance is not used by score 'nmi'; pass variance=None"):
        direct_surface(NMI(), local, window, variance)
    with pytest.raises(ValueError, match="variance must be given for score 'enmi', got None"):
        direct_surface(ENMI(), local, window)
    with pytest.raises(ValueError, match="variance must be given for score 'ecr', got None"):
        direct_surface("ecr", local, window)
    with pytest.raises(ValueError, match="model_variance must be 'estimate', a number >= 0"):
        ecr_surface(local, window, variance, model_variance=-2.0)
    with pytest.raises(ValueError, match="variance must be a number or a tensor"):
        ecr_surface(local, window, None)
    with pytest.raises(ValueError, match="reference must be at least as large as captured"):
        ncc_surface(local, window[..., :, :3])


@pytest.mark.parametrize("masks", ["none", "local", "window", "both"])
def test_ecr_fft_surface_equals_direct_loop(masks, dtype):
    local, window, variance, captured_mask, reference_mask = _case(torch.float64)
    # One window per sample, so a swapped sample/window pairing fails too.
    window = torch.cat([window, window.flip(-1) * 0.5 + 60])
    chosen = {
        "captured_mask": captured_mask if masks in ("local", "both") else None,
        "reference_mask": torch.cat([reference_mask, reference_mask.flip(-2)]) if masks in ("window", "both") else None,
    }
    fast = ecr_surface(local.to(dtype), window.to(dtype), variance.to(dtype), bins=12, model_variance=3.0, **chosen)
    slow = _direct(local, window, variance, metric="ecr", bins=12, model_variance=3.0, **chosen)
    assert fast.score.shape == (2, 8, 9)
    assert fast.score.dtype == dtype
    tolerance = {"rtol": 1e-9, "atol": 1e-9} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 2e-3}
    torch.testing.assert_close(fast.score.double(), slow.score, **tolerance)
    torch.testing.assert_close(fast.overlap.double(), slow.overlap, rtol=0, atol=0)
    if masks in ("none", "local"):
        # The noisy cut of sample 0 sits at window cell (3, 4) (the window mask hides part of it).
        assert divmod(int(fast.score[0].flatten().argmax()), 9) == (3, 4)


@pytest.mark.parametrize("masks", ["none", "local", "window", "both"])
def test_reliability_weighted_enmi_surface_equals_direct_loop(masks, dtype):
    local, window, variance, captured_mask, reference_mask = _case(torch.float64)
    variance = variance**2  # 4 to 3800: strongly non-uniform
    chosen = {
        "captured_mask": captured_mask if masks in ("local", "both") else None,
        "reference_mask": reference_mask if masks in ("window", "both") else None,
    }
    fast = enmi_surface(local.to(dtype), window.to(dtype), variance.to(dtype), bins=12, reliability=True, **chosen)
    slow = _direct(local, window, variance, metric="enmi", bins=12, reliability=True, **chosen)
    plain = _direct(local, window, variance, metric="enmi", bins=12, **chosen)
    tolerance = {"rtol": 1e-9, "atol": 1e-9} if dtype == torch.float64 else {"rtol": 1e-4, "atol": 1e-4}
    torch.testing.assert_close(fast.score.double(), slow.score, **tolerance)
    torch.testing.assert_close(fast.overlap.double(), slow.overlap, rtol=0, atol=0)
    assert not torch.allclose(slow.score, plain.score, rtol=1e-3)


def test_float32_surface_scores_a_nearly_constant_overlap_like_nmi():
    # A flat patch with one odd pixel: the joint entropy is tiny but real, and NMI is 2, not the constant-overlap 1.
    window = torch.full((1, 1, 210, 210), 100.0)
    window[..., 105, 105] = 200.0
    local = window[..., 5:205, 5:205].clone()
    expected = nmi(local.double(), local.double(), kernel="hard")
    assert expected.item() == pytest.approx(2.0)
    surface = nmi_surface(local, window, kernel="hard")
    assert surface.score[0, 5, 5].item() == pytest.approx(2.0, abs=1e-2)  # float32 round-off of a 2e-4 entropy
    # A truly constant overlap still scores 1 (the odd pixel outside the local footprint).
    flat = torch.full((1, 1, 210, 210), 100.0)
    assert nmi_surface(flat[..., :200, :200], flat, kernel="hard").score[0, 5, 5].item() == 1.0


@pytest.mark.parametrize("masks", ["none", "both"])
def test_ecr_linear_fft_surface_equals_direct_loop(masks, dtype):
    local, window, variance, captured_mask, reference_mask = _case(torch.float64)
    chosen = {"captured_mask": captured_mask, "reference_mask": reference_mask} if masks == "both" else {}
    fast = ecr_surface(local.to(dtype), window.to(dtype), variance.to(dtype), response="linear", **chosen)
    slow = _direct(local, window, variance, metric="ecr", response="linear", **chosen)
    tolerance = {"rtol": 1e-9, "atol": 1e-9} if dtype == torch.float64 else {"rtol": 1e-3, "atol": 1e-3}
    torch.testing.assert_close(fast.score.double(), slow.score, **tolerance)
    torch.testing.assert_close(fast.overlap.double(), slow.overlap, rtol=0, atol=0)


def test_float32_surfaces_score_a_constant_overlap_in_a_textured_window_as_one():
    # FFT round-off from the texture around a constant region must not make its placements look informative.
    generator = torch.Generator().manual_seed(0)
    window = torch.rand(1, 1, 90, 90, generator=generator) * 256
    window[..., 10:80, 10:80] = 100.0
    local = torch.full((1, 1, 60, 60), 100.0)
    inside = (0, slice(10, 21), slice(10, 21))  # placements whose footprint lies in the constant region
    assert (nmi_surface(local, window, kernel="hard").score[inside] == 1.0).all()
    assert (enmi_surface(local, window, 1e-4).score[inside] == 1.0).all()


@pytest.mark.parametrize("surface", ["ncc", "ecr_linear"])
def test_moment_surfaces_of_a_batch_against_one_shared_reference_equal_per_sample_calls(surface, dtype):
    generator = torch.Generator().manual_seed(4)
    reference = (torch.rand(1, 1, 19, 23, generator=generator, dtype=torch.float64) * 256).to(dtype)
    local = torch.stack([reference[0, :, 2:12, 3:16], reference[0, :, 6:16, 8:21]]) + 3
    variance = torch.linspace(4.0, 40.0, 13, dtype=dtype).expand(1, 1, 10, 13)

    def call(captured):
        if surface == "ncc":
            return ncc_surface(captured, reference).score
        return ecr_surface(captured, reference, variance, response="linear").score

    batched = call(local)
    for sample in range(2):
        torch.testing.assert_close(batched[sample], call(local[sample : sample + 1])[0])
    assert [divmod(int(batched[sample].flatten().argmax()), 11) for sample in range(2)] == [(2, 3), (6, 8)]
