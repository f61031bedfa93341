"""ECR's model variance estimated from the data (``model_variance="estimate"``): the REML estimate, where it is read
(aligned pairs, surfaces, the two-stage search) and that the scores are ECR's with it."""

import math

import numpy as np
import pytest
import torch
from scipy.optimize import minimize_scalar

from enmi_torch import ECR, localize
from enmi_torch.binning import hard_bin_index
from enmi_torch.functional import ecr, ecr_surface
from enmi_torch.scores import direct_surface
from enmi_torch.scores.ecr import ecr_model_variance, ecr_surface_model_variance
from enmi_torch.scores.ecr_model_variance import default_model_variance
from enmi_torch.scores.ecr_placements import cheap_value_range

RANGE = (0.0, 256.0)


def _reml_reference(values, reference, noise, bins, response) -> float:
    """The REML ``tau^2`` of one aligned pair by a bounded 1-D search on the textbook restricted likelihood.

    ``l(t) = -1/2 (log|V| + log|X' V^-1 X| + r' V^-1 r)``, ``V = diag(s + t)``, ``r`` the GLS residuals, ``X`` the
    one-hot reference bins (``"binned"``) or ``[1, reference]`` (``"linear"``), floored at ``bin_width^2 / 12``.
    """
    values, reference, noise = (np.asarray(part, np.float64).ravel() for part in (values, reference, noise))
    if response == "binned":
        cells = hard_bin_index(torch.from_numpy(reference), bins, RANGE).numpy()
        design = (cells[:, None] == np.unique(cells)[None, :]).astype(np.float64)
    else:
        design = np.stack([np.ones_like(reference), reference], 1)

    def negative(log_tau2: float) -> float:
        weight = 1 / (noise + math.exp(log_tau2))
        normal = design.T @ (weight[:, None] * design)
        beta = np.linalg.solve(normal, design.T @ (weight * values))
        residual = values - design @ beta
        return 0.5 * (np.log(noise + math.exp(log_tau2)).sum() + np.linalg.slogdet(normal)[1] + weight @ residual**2)

    floor = default_model_variance(bins, RANGE)
    best = minimize_scalar(
        negative, bounds=(math.log(floor), math.log(100 * values.var())), method="bounded", options={"xatol": 1e-9}
    )
    return max(floor, math.exp(best.x))


def _flat(*tensors):
    """``(..., B, N)`` flat samples as ``(..., B, 1, N)``, the layout the scores take them in."""
    return tuple(tensor[..., None, :] for tensor in tensors)


def _misfit_pairs(tau2, generator, *, batch=6, pixels=3000, bins=64, response="binned"):
    """Aligned pairs whose captured values are the model's means plus noise of ``s_n + tau^2``, exactly."""
    reference = torch.rand(batch, pixels, generator=generator, dtype=torch.float64) * 256
    noise = 10 + 990 * torch.rand(batch, pixels, generator=generator, dtype=torch.float64)
    if response == "binned":
        # One mean per reference bin (non-monotonic), so the misfit about the bin means is the drawn one.
        means = 40 + 120 * torch.sin(hard_bin_index(reference, bins, RANGE).double() * 0.7)
    else:
        means = 30 + 0.6 * reference
    captured = means + torch.randn(batch, pixels, generator=generator, dtype=torch.float64) * (noise + tau2).sqrt()
    return captured, reference, noise


@pytest.mark.parametrize("response", ["binned", "linear"])
@pytest.mark.parametrize("tau2", [50.0, 400.0, 3000.0])
def test_the_estimate_recovers_a_known_misfit_variance(tau2, response, generator):
    captured, reference, noise = _flat(*_misfit_pairs(tau2, generator, response=response))
    estimate = ecr_model_variance(captured, reference, noise, bins=64, response=response)
    assert estimate.shape == (6,) and estimate.dtype == torch.float64
    assert abs(float(estimate.mean()) - tau2) < 0.1 * tau2


@pytest.mark.parametrize("response", ["binned", "linear"])
def test_the_estimate_is_the_restricted_likelihood_maximum(response, generator):
    captured, reference, noise = _misfit_pairs(300.0, generator, batch=3, pixels=500, bins=16, response=response)
    noise[1, :250] = noise[1, :250] / 50  # some pixels far quieter than the rest
    estimate = ecr_model_variance(*_flat(captured, reference, noise), bins=16, response=response)
    expected = [_reml_reference(captured[b], reference[b], noise[b], 16, response) for b in range(3)]
    torch.testing.assert_close(estimate, torch.tensor(expected, dtype=torch.float64), rtol=1e-6, atol=0)


def test_without_misfit_beyond_the_noise_the_estimate_is_the_quantisation_floor(generator):
    reference = torch.rand(3, 1, 40, 40, generator=generator, dtype=torch.float64) * 256
    variance = 400.0 + 200 * torch.rand(3, 1, 40, 40, generator=generator, dtype=torch.float64)
    # The stated variance overstates the noise: the restricted likelihood wants tau^2 below 0.
    captured = reference + 5 * torch.randn(3, 1, 40, 40, generator=generator, dtype=torch.float64)
    estimate = ecr_model_variance(captured, reference, variance, bins=16)
    assert torch.equal(estimate, torch.full((3,), default_model_variance(16, RANGE), dtype=torch.float64))
    # Fewer valid pixels than occupied bins: nothing to estimate from, the floor again.
    few = torch.zeros(3, 1, 40, 40, dtype=torch.bool)
    few[..., 0, :3] = True
    captured = captured + 500 * torch.randn(3, 1, 40, 40, generator=generator, dtype=torch.float64)
    estimate = ecr_model_variance(captured, reference, variance, bins=256, valid_mask=few)
    assert torch.equal(estimate, torch.full((3,), default_model_variance(256, RANGE), dtype=torch.float64))


def test_a_given_model_variance_is_used_as_it_is(generator, dtype):
    captured, reference, noise = (
        part.to(dtype) for part in _flat(*_misfit_pairs(400.0, generator, batch=2, pixels=300))
    )
    for given, expected in ((12.5, 12.5), (None, default_model_variance(32, RANGE)), (0, 0.0)):
        assert torch.equal(
            ecr_model_variance(captured, reference, noise, model_variance=given),
            torch.full((2,), expected, dtype=torch.float64),
        )
        assert ECR(model_variance=given).model_variance_of(captured, reference, noise).tolist() == [expected] * 2


def _images(dtype, generator, *, batch=3, shared=True):
    """Non-square captured images cut from non-square windows (unequal radii) with a misfit and per-pixel noise."""
    references = torch.rand(1 if shared else batch, 1, 27, 34, generator=generator, dtype=torch.float64) * 256
    variance = 20 + 600 * torch.rand(batch, 1, 14, 18, generator=generator, dtype=torch.float64)
    tops, lefts = [4, 9, 0][:batch], [11, 2, 16][:batch]
    sections = torch.stack(
        [
            references[0 if shared else sample, :, top : top + 14, left : left + 18]
            for sample, (top, left) in enumerate(zip(tops, lefts, strict=True))
        ]
    )
    misfit = torch.randn(batch, 1, 14, 18, generator=generator, dtype=torch.float64) * 18  # tau^2 = 324
    captured = (
        230
        - 0.8 * sections
        + misfit
        + variance.sqrt() * torch.randn(batch, 1, 14, 18, generator=generator, dtype=torch.float64)
    )
    return captured.to(dtype), references.to(dtype), variance.to(dtype), list(zip(tops, lefts, strict=True))


@pytest.mark.parametrize("shared", [True, False])
def test_a_surface_reads_its_estimate_at_the_first_pass_peak_and_is_ecr_with_it(dtype, generator, shared):
    captured, references, variance, truth = _images(dtype, generator, shared=shared)
    reference_mask = torch.ones(1, 1, 27, 34, dtype=torch.bool)
    reference_mask[..., 5, 13:20] = False  # masked cells under the first image's true placement
    score = ECR(bins=12, model_variance="estimate")
    tau2 = score.surface_model_variance(captured, references, variance, reference_mask=reference_mask)
    surface = score.surface(captured, references, variance, reference_mask=reference_mask)
    for sample, (top, left) in enumerate(truth):
        window = references[sample if not shared else 0 : (sample if not shared else 0) + 1]
        section = window[..., top : top + 14, left : left + 18]
        valid = reference_mask[..., top : top + 14, left : left + 18]
        # The images are clear enough that the cheap first pass finds the true placement.
        at_truth = score.model_variance_of(
            captured[sample : sample + 1], section, variance[sample : sample + 1], valid_mask=valid
        )
        torch.testing.assert_close(tau2[sample : sample + 1], at_truth, rtol=1e-6, atol=0)
        assert 150 < float(tau2[sample]) < 700
        fixed = ecr_surface(
            captured[sample : sample + 1],
            window,
            variance[sample : sample + 1],
            bins=12,
            model_variance=float(tau2[sample]),
            reference_mask=reference_mask,
        )
        tolerance = {"rtol": 1e-9, "atol": 1e-9} if dtype == torch.float64 else {"rtol": 1e-4, "atol": 1e-4}
        torch.testing.assert_close(surface.score[sample], fixed.score[0], **tolerance)
        assert divmod(int(surface.score[sample].argmax()), surface.score.shape[-1]) == (top, left)


def test_fast_surface_equals_the_direct_loop_with_masks_float64(generator):
    captured, references, variance, _ = _images(torch.float64, generator, shared=False)
    captured_mask = torch.rand(3, 1, 14, 18, generator=generator) > 0.2
    reference_mask = torch.rand(3, 1, 27, 34, generator=generator) > 0.1
    reference_mask[..., :, :6] = False  # placements on the left overlap unmapped cells
    masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
    score = ECR(bins=10, value_range=(0.0, 300.0), model_variance="estimate")
    fast = score.surface(captured, references, variance, **masks)
    tau2 = score.surface_model_variance(captured, references, variance, **masks)
    delta2 = score.surface_response_variance(captured, references, variance, **masks)
    for sample in range(3):
        # The direct loop: ECR of every aligned pair with the surface's tau^2 and delta^2 of that image.
        expected = torch.zeros(14, 17, dtype=torch.float64)
        for row in range(14):
            for col in range(17):
                section = references[sample : sample + 1, :, row : row + 14, col : col + 18]
                valid = (
                    captured_mask[sample : sample + 1]
                    & reference_mask[sample : sample + 1, :, row : row + 14, col : col + 18]
                )
                if bool(valid.any()):
                    expected[row, col] = ecr(
                        captured[sample : sample + 1],
                        section,
                        variance[sample : sample + 1],
                        bins=10,
                        value_range=(0.0, 300.0),
                        model_variance=float(tau2[sample]),
                        response_variance=float(delta2[sample]),
                        valid_mask=valid,
                    )[0]
        torch.testing.assert_close(fast.score[sample], expected, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(
        direct_surface(score, captured, references, variance, **masks).score, fast.score, rtol=1e-6, atol=1e-6
    )


def test_batched_equals_one_by_one(dtype, generator):
    captured, references, variance, _ = _images(dtype, generator, shared=True)
    score = ECR(bins=12, model_variance="estimate")
    surface = score.surface(captured, references, variance)
    values = score(captured, captured.flip(0), variance)
    for sample in range(3):
        one = slice(sample, sample + 1)
        torch.testing.assert_close(score.surface(captured[one], references, variance[one]).score, surface.score[one])
        torch.testing.assert_close(score(captured[one], captured.flip(0)[one], variance[one]), values[one])


def test_values_use_each_pairs_own_estimate_and_reduce_to_fixed_ecr(dtype, generator):
    captured, reference, noise = (
        part.to(dtype) for part in _flat(*_misfit_pairs(400.0, generator, batch=2, pixels=900))
    )
    candidates = torch.stack([reference, reference.roll(1, 0), reference.flip(-1)])  # (C, B, 1, N)
    tau2 = ecr_model_variance(captured, candidates, noise, bins=64)
    assert tau2.shape == (3, 2) and bool((tau2[1:] > 4 * tau2[0]).all())  # misaligned: a larger misfit
    values = ecr(captured, candidates, noise, bins=64, model_variance="estimate")
    for candidate in range(3):
        for sample in range(2):
            fixed = ecr(
                captured[sample : sample + 1],
                candidates[candidate, sample : sample + 1],
                noise[sample : sample + 1],
                bins=64,
                model_variance=float(tau2[candidate, sample]),
            )
            torch.testing.assert_close(values[candidate, sample : sample + 1], fixed)


def test_gradients_hold_the_estimate_fixed_and_are_finite(generator):
    captured, reference, noise = _flat(*_misfit_pairs(400.0, generator, batch=2, pixels=400, bins=16))
    mask = torch.rand(2, 1, 400, generator=generator) > 0.1
    tau2 = ecr_model_variance(captured, reference, noise, bins=16, valid_mask=mask)
    grads = []
    for model_variance in ("estimate", tau2[:, None]):
        leaf_captured, leaf_noise = captured.clone().requires_grad_(), noise.clone().requires_grad_()
        if isinstance(model_variance, str):
            value = ECR(bins=16, model_variance="estimate").loss(
                leaf_captured, reference, leaf_noise, valid_mask=mask, reduction="sum"
            )
        else:
            value = sum(
                -ecr(
                    leaf_captured[b : b + 1],
                    reference[b : b + 1],
                    leaf_noise[b : b + 1],
                    bins=16,
                    model_variance=float(tau2[b]),
                    valid_mask=mask[b : b + 1],
                ).sum()
                for b in range(2)
            )
        value.backward()
        grads.append((leaf_captured.grad, leaf_noise.grad))
    for estimated, fixed in zip(*grads, strict=True):
        assert bool(torch.isfinite(estimated).all())
        torch.testing.assert_close(estimated, fixed, rtol=1e-9, atol=1e-12)
    # With tau^2 held at the estimate, ECR is a smooth function of the captured values and variances.
    assert torch.autograd.gradcheck(
        lambda values, variances: ecr(
            values, reference[:1], variances, bins=16, model_variance=float(tau2[0]), valid_mask=mask[:1]
        ),
        (captured[:1].clone().requires_grad_(), noise[:1].clone().requires_grad_()),
    )


def test_the_two_stage_search_scores_as_the_exhaustive_one(generator):
    captured, references, variance, _ = _images(torch.float64, generator, batch=2, shared=True)
    options = {
        "score": ECR(bins=12, model_variance="estimate"),
        "shifts": (6, 8),
        "around": (17, 14),
        "yaws": [-30.0, 0.0, 90.0],
    }
    exhaustive = localize(captured, references, variance, **options).surface
    staged = localize(captured, references, variance, search="two_stage", **options).surface
    rescored = torch.isfinite(staged)
    assert int(rescored.sum()) > 27
    torch.testing.assert_close(staged[rescored], exhaustive[rescored], rtol=1e-9, atol=1e-9)


def test_each_yaw_has_its_own_estimate(generator):
    captured, references, variance, _ = _images(torch.float64, generator, batch=1)
    from enmi_torch.localization.candidates import rotate_captured

    rotated, rotated_variance, rotated_valid = rotate_captured(
        captured, variance, torch.ones_like(captured, dtype=torch.bool), [0.0, 20.0], "nearest"
    )
    tau2 = ECR(bins=12, model_variance="estimate").surface_model_variance(
        rotated, references, rotated_variance, captured_mask=rotated_valid
    )
    assert float(tau2[1]) > 2 * float(tau2[0])  # the wrong yaw explains less of the image
    surface = localize(
        captured,
        references,
        variance,
        score=ECR(bins=12, model_variance="estimate"),
        shifts=(6, 8),
        around=(17, 14),
        yaws=[0.0, 20.0],
    ).surface
    for yaw in range(2):
        fixed = localize(
            captured,
            references,
            variance,
            score=ECR(bins=12, model_variance=float(tau2[yaw])),
            shifts=(6, 8),
            around=(17, 14),
            yaws=[0.0, 20.0],
        ).surface
        torch.testing.assert_close(surface[0, yaw], fixed[0, yaw], rtol=1e-9, atol=1e-9)


def test_the_first_pass_is_the_cheap_stage_of_the_window(generator):
    window = torch.arange(400.0, dtype=torch.float64).reshape(1, 1, 20, 20)
    assert cheap_value_range(window, torch.ones_like(window, dtype=torch.bool)) == pytest.approx((7.98, 391.02))
    captured, references, variance, truth = _images(torch.float64, generator, batch=1)
    tau2 = ecr_surface_model_variance(captured, references, variance, bins=12)
    assert tau2.shape == (1,)
    top, left = truth[0]
    expected = ecr_model_variance(captured, references[..., top : top + 14, left : left + 18], variance, bins=12)
    torch.testing.assert_close(tau2, expected, rtol=1e-6, atol=0)


def test_the_first_pass_leaves_out_placements_overlapping_less_than_half_the_image(generator):
    window = torch.rand(1, 1, 30, 30, generator=generator, dtype=torch.float64) * 256
    captured = torch.rand(1, 1, 10, 10, generator=generator, dtype=torch.float64) * 256  # not in the map
    reference_mask = torch.ones(1, 1, 30, 30, dtype=torch.bool)
    # At placement (15, 15) the three rows that land on mapped cells match the captured image exactly.
    window[..., 15:18, 15:25] = captured[..., :3, :]
    reference_mask[..., 18:25, 15:25] = False
    tau2 = ecr_surface_model_variance(captured, window, 1.0, reference_mask=reference_mask)
    assert float(tau2[0]) > 1000  # read at an unrelated placement, not at the 30 % match
    exact = ecr_model_variance(captured[..., :3, :], window[..., 15:18, 15:25], 1.0)
    assert float(exact[0]) == default_model_variance(32, RANGE)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("auto", "model_variance must be 'estimate', a number >= 0 or None, got 'auto'"),
        (-1.0, "model_variance must be 'estimate', a number >= 0 or None, got -1.0"),
        (True, "model_variance must be 'estimate', a number >= 0 or None, got True"),
        (math.inf, "model_variance must be finite, got inf"),
    ],
)
def test_bad_model_variances_are_refused(value, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        ECR(model_variance=value)
    with pytest.raises(ValueError, match="model_variance must be"):
        ecr_model_variance(torch.ones(1, 1, 4), torch.ones(1, 1, 4), 1.0, model_variance=value)
