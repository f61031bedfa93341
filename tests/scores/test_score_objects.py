"""Score objects: each equals its family's functions, its surface equals the direct loop; options, errors, pickling."""

import pickle

import numpy as np
import pytest
import torch

from enmi_torch import ECR, ENMI, NCC, NMI, ECRLoss, ENMILoss, Mixture, NMILoss, ScoreLoss
from enmi_torch.functional import (
    ecr,
    ecr_loss,
    ecr_surface,
    enmi,
    enmi_loss,
    enmi_surface,
    gaussian_log_prior,
    mixture_information,
    mixture_loss,
    mixture_surface,
    ncc,
    ncc_loss,
    ncc_surface,
    nmi,
    nmi_loss,
    nmi_surface,
)
from enmi_torch.losses import MixtureLoss
from enmi_torch.scores import Score, as_score, direct_surface
from enmi_torch.variance import ConstantVariance

RANGE = (10.0, 250.0)  # not the default, so that a dropped option shows


def _prior(bins, dtype=torch.float64):
    return gaussian_log_prior(120.0, 50.0, bins, RANGE, dtype=dtype)


# (score, its functional value, surface and loss with the same options); options differ from the defaults.
def _families():
    prior = _prior(12)
    return [
        (
            ECR(bins=12, value_range=RANGE, model_variance=3.0),
            lambda c, r, v, **k: ecr(c, r, v, bins=12, value_range=RANGE, model_variance=3.0, **k),
            lambda c, r, v, **k: ecr_surface(c, r, v, bins=12, value_range=RANGE, model_variance=3.0, **k),
            lambda c, r, v, **k: ecr_loss(c, r, v, bins=12, value_range=RANGE, model_variance=3.0, **k),
        ),
        (
            ECR(bins=10, response="linear"),
            lambda c, r, v, **k: ecr(c, r, v, bins=10, response="linear", **k),
            lambda c, r, v, **k: ecr_surface(c, r, v, bins=10, response="linear", **k),
            lambda c, r, v, **k: ecr_loss(c, r, v, bins=10, response="linear", **k),
        ),
        (
            ENMI(bins=12, value_range=RANGE, kernel="density", log_prior=prior),
            lambda c, r, v, **k: enmi(c, r, v, bins=12, value_range=RANGE, kernel="density", log_prior=prior, **k),
            lambda c, r, v, **k: enmi_surface(
                c, r, v, bins=12, value_range=RANGE, kernel="density", log_prior=prior, **k
            ),
            lambda c, r, v, **k: enmi_loss(c, r, v, bins=12, value_range=RANGE, kernel="density", log_prior=prior, **k),
        ),
        (
            ENMI(bins=12, reliability=True),
            lambda c, r, v, **k: enmi(c, r, v, bins=12, reliability=True, **k),
            lambda c, r, v, **k: enmi_surface(c, r, v, bins=12, reliability=True, **k),
            lambda c, r, v, **k: enmi_loss(c, r, v, bins=12, reliability=True, **k),
        ),
        (
            NMI(bins=12, value_range=RANGE),
            lambda c, r, v, **k: nmi(c, r, bins=12, value_range=RANGE, **k),
            lambda c, r, v, **k: nmi_surface(c, r, bins=12, value_range=RANGE, **k),
            lambda c, r, v, **k: nmi_loss(c, r, bins=12, value_range=RANGE, **k),
        ),
        (
            NCC(),
            lambda c, r, v, **k: ncc(c, r, **k),
            lambda c, r, v, **k: ncc_surface(c, r, **k),
            lambda c, r, v, **k: ncc_loss(c, r, **k),
        ),
        (
            Mixture(bins=8, value_range=RANGE, em_steps=1),
            lambda c, r, v, **k: mixture_information(c, r, v, bins=8, value_range=RANGE, em_steps=1, **k),
            lambda c, r, v, **k: mixture_surface(c, r, v, bins=8, value_range=RANGE, em_steps=1, **k),
            lambda c, r, v, **k: mixture_loss(c, r, v, bins=8, value_range=RANGE, em_steps=1, **k),
        ),
    ]


FAMILY_IDS = ["ecr", "ecr_linear", "enmi_prior", "enmi_reliability", "nmi", "ncc", "mixture"]


def _pairs(dtype):
    """Aligned pairs (B = 2) of 7 x 10 with a per-pixel variance, a mask and a second candidate reference."""
    generator = torch.Generator().manual_seed(7)
    reference = torch.rand(2, 1, 7, 10, generator=generator, dtype=torch.float64) * 240 + 10
    captured = reference * 0.9 + 15 + 8 * torch.randn(2, 1, 7, 10, generator=generator, dtype=torch.float64)
    variance = torch.rand(2, 1, 7, 10, generator=generator, dtype=torch.float64) * 50 + 10
    valid = torch.rand(2, 1, 7, 10, generator=generator) > 0.2
    candidates = torch.stack([reference, reference.flip(-1)])
    return captured.to(dtype), candidates.to(dtype), variance.to(dtype), valid


def _placements(dtype):
    """A non-square captured image (6 x 9) in a reference that leaves unequal radii (rows 3, columns 2)."""
    generator = torch.Generator().manual_seed(11)
    reference = torch.rand(1, 1, 12, 13, generator=generator, dtype=torch.float64) * 240 + 10
    captured = reference[..., 2:8, 3:12] + 6 * torch.randn(2, 1, 6, 9, generator=generator, dtype=torch.float64)
    variance = torch.rand(2, 1, 6, 9, generator=generator, dtype=torch.float64) * 40 + 5
    captured_mask = torch.rand(2, 1, 6, 9, generator=generator) > 0.15
    reference_mask = torch.rand(1, 1, 12, 13, generator=generator) > 0.1
    return captured.to(dtype), reference.to(dtype), variance.to(dtype), captured_mask, reference_mask


@pytest.mark.parametrize("family", range(7), ids=FAMILY_IDS)
def test_score_object_equals_its_functions(family, dtype):
    score, value, surface, loss = _families()[family]
    captured, candidates, variance, valid = _pairs(dtype)
    given = variance if score.uses_variance else None
    # Bit for bit: the object calls the same function with the same options.
    assert torch.equal(
        score(captured, candidates, given, valid_mask=valid), value(captured, candidates, variance, valid_mask=valid)
    )
    for reduction in ("none", "sum"):
        expected = loss(captured, candidates[0], variance, valid_mask=valid, reduction=reduction)
        assert torch.equal(score.loss(captured, candidates[0], given, valid_mask=valid, reduction=reduction), expected)
    local, reference, local_variance, captured_mask, reference_mask = _placements(dtype)
    masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
    given = local_variance if score.uses_variance else None
    fast, expected = score.surface(local, reference, given, **masks), surface(local, reference, local_variance, **masks)
    assert torch.equal(fast.score, expected.score) and torch.equal(fast.overlap, expected.overlap)


@pytest.mark.parametrize("family", range(7), ids=FAMILY_IDS)
def test_direct_surface_of_every_family_equals_its_fft_surface_on_a_non_square_image(family):
    score = _families()[family][0]
    local, reference, variance, captured_mask, reference_mask = _placements(torch.float64)
    masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
    given = variance if score.uses_variance else None
    fast = score.surface(local, reference, given, **masks)
    slow = direct_surface(score, local, reference, given, **masks)
    assert fast.score.shape == slow.score.shape == (2, 7, 5)
    torch.testing.assert_close(fast.overlap, slow.overlap, rtol=0, atol=0)
    # The mixture surface scores its best peaks exactly and leaves the others at -inf.
    scored = torch.isfinite(fast.score)
    assert int(scored.sum()) >= (18 if isinstance(score, Mixture) else 70)
    torch.testing.assert_close(fast.score[scored], slow.score[scored], rtol=0, atol=1e-9)
    # Each entry is the score of the aligned pair under it, over the pixels valid in both.
    sample, row, col = 1, 3, 1
    section = reference[..., row : row + 6, col : col + 9]
    valid = captured_mask[sample : sample + 1] & reference_mask[..., row : row + 6, col : col + 9]
    if score.options.get("model_variance") == "estimate":  # a surface's tau^2 is one per captured image
        tau2 = score.surface_model_variance(local, reference, given, **masks)
        score = score.replace(model_variance=float(tau2[sample]))
    if score.options.get("response") == "shrunk":  # and so is the shrunk response's delta^2
        delta2 = score.surface_response_variance(local, reference, given, **masks)
        score = score.replace(response_variance=float(delta2[sample]))
    if not score.options.get("reliability", False):  # reliability is estimated over the whole image on a surface
        pair = score(
            local[sample : sample + 1], section, None if given is None else given[sample : sample + 1], valid_mask=valid
        )
        torch.testing.assert_close(slow.score[sample, row, col], pair[0], rtol=0, atol=1e-12)


def test_direct_surface_scores_placements_without_overlap_as_unrelated_images():
    local, reference, variance, _, _ = _placements(torch.float64)
    reference_mask = torch.ones(1, 1, 12, 13, dtype=torch.bool)
    reference_mask[..., :, :9] = False  # the first column of placements sees no valid cell
    for score, empty in [(ENMI(), 1.0), (NMI(), 1.0), (ECR(), 0.0), (NCC(), 0.0), (Mixture(), 0.0)]:
        given = variance if score.uses_variance else None
        slow = direct_surface(score, local, reference, given, reference_mask=reference_mask)
        assert bool((slow.overlap[:, :, 0] == 0).all()) and bool((slow.score[:, :, 0] == empty).all())
        assert score.empty_score == empty


def test_as_score_takes_objects_and_names():
    score = ENMI(bins=8)
    assert as_score(score) is score
    assert as_score("ecr") == ECR() and as_score("enmi") == ENMI() and as_score("nmi") == NMI()
    assert as_score("ncc") == NCC() and as_score("mixture") == Mixture()
    with pytest.raises(
        ValueError, match=r"score must be a Score or one of \['ecr', 'enmi', 'mixture', 'ncc', 'nmi'\], got 'mi'"
    ):
        as_score("mi")
    with pytest.raises(ValueError, match="score must be a Score or one of"):
        as_score(ECR)


def test_replace_changes_options_checks_them_again_and_leaves_the_original():
    score = ECR(bins=16, model_variance=2.0)
    changed = score.replace(bins=8, value_range=(0.0, 1.0))
    assert changed == ECR(bins=8, value_range=(0.0, 1.0), model_variance=2.0)
    assert score == ECR(bins=16, model_variance=2.0) and score.bins == 16
    with pytest.raises(ValueError, match="bins must be an int >= 2"):
        score.replace(bins=1)
    with pytest.raises(TypeError, match=r"ECR has no option\(s\) \['kernel'\]; its options: \['bins', 'value_range'"):
        score.replace(kernel="mass")
    assert type(score)(**score.options) == score
    assert NMI.option_names() == ("bins", "value_range", "kernel", "reference_kernel") and NCC.option_names() == ()


def test_repr_names_every_option_and_round_trips():
    assert (
        repr(ECR())
        == "ECR(bins=32, value_range=(0.0, 256.0), model_variance='estimate', response='shrunk', misfit='independent', "
        "response_variance='estimate', saturation='value_range')"
    )
    assert repr(NCC()) == "NCC()"
    assert repr(Mixture(em_steps=2)) == "Mixture(bins=32, value_range=(0.0, 256.0), em_steps=2)"
    for score in (
        ECR(bins=8, response="linear"),
        ECR(misfit="correlated"),
        ENMI(kernel="truncated", reliability=True),
        NMI(kernel="xu"),
        NCC(),
    ):
        assert eval(repr(score)) == score
    assert repr(ENMI(bins=12, log_prior=_prior(12))).startswith(
        "ENMI(bins=12, value_range=(0.0, 256.0), kernel='mass', log_prior=tensor((12,), torch.float64)"
    )


def test_equality_and_hash_follow_the_options():
    prior = _prior(12)
    assert ENMI(bins=12, log_prior=prior) == ENMI(bins=12, log_prior=prior.clone())
    assert ENMI(bins=12, log_prior=prior) != ENMI(bins=12, log_prior=prior + 1)
    assert ECR() != ENMI() and ECR(bins=8) != ECR(bins=16) and ECR() != "ecr"
    assert len({ECR(), ECR(), ECR(bins=8), NCC(), NCC()}) == 3


def test_scores_pickle_with_their_options():
    for score in (
        ECR(bins=8, model_variance=1.5),
        ENMI(bins=12, log_prior=_prior(12)),
        NMI(),
        NCC(),
        Mixture(em_steps=1),
    ):
        copy = pickle.loads(pickle.dumps(score))
        assert copy == score and repr(copy) == repr(score) and copy.options.keys() == score.options.keys()


@pytest.mark.parametrize(
    ("build", "error", "message"),
    [
        (lambda: ECR(bins=1), ValueError, "bins must be an int >= 2"),
        (lambda: ECR(bins=8.0), TypeError, "bins must be an int >= 2, got float"),
        (lambda: ECR(value_range=(3.0, 1.0)), ValueError, "value_range must be finite with low < high"),
        (
            lambda: ECR(model_variance=-1.0),
            ValueError,
            "model_variance must be 'estimate', a number >= 0 or None, got -1",
        ),
        (lambda: ECR(response="quadratic"), ValueError, r"response must be one of \['shrunk', 'binned', 'linear'\]"),
        (lambda: ECR(kernel="mass"), TypeError, "unexpected keyword argument 'kernel'"),
        (lambda: ECR(32), TypeError, "positional"),
        (lambda: ENMI(kernel="hard"), ValueError, r"kernel must be one of \['mass', 'density', 'truncated'\]"),
        (lambda: ENMI(reliability=1), TypeError, "reliability must be True or False, got 1"),
        (lambda: ENMI(log_prior=torch.zeros(5)), ValueError, r"log_prior must have shape \(32,\)"),
        (lambda: ENMI(log_prior=torch.zeros(32, dtype=torch.long)), TypeError, "log_prior must be a floating-point"),
        (lambda: ENMI(log_prior=torch.full((32,), float("nan"))), ValueError, "log_prior must hold finite values"),
        (lambda: ENMI(reference_kernel="mass"), ValueError, "reference_kernel must be one of"),
        (lambda: NMI(kernel="mass"), ValueError, r"kernel must be one of \['hard', 'triangular', 'xu'\]"),
        (lambda: Mixture(em_steps=-1), ValueError, "em_steps must be an int >= 0"),
        (lambda: NCC(bins=8), TypeError, "unexpected keyword argument 'bins'"),
    ],
)
def test_options_are_checked_when_the_score_is_built(build, error, message):
    with pytest.raises(error, match=message):
        build()


def test_a_variance_is_required_by_the_scores_that_use_one_and_refused_by_the_others():
    captured, candidates, variance, _ = _pairs(torch.float64)
    local, reference, local_variance, _, _ = _placements(torch.float64)
    for score in (ECR(), ENMI(), Mixture(), NMI(), NCC()):
        if score.uses_variance:
            message, given, local_given = f"variance must be given for score '{score.name}', got None", None, None
        else:
            message, given, local_given = f"variance is not used by score '{score.name}'", variance, local_variance
        with pytest.raises(ValueError, match=message):
            score(captured, candidates[0], given)
        with pytest.raises(ValueError, match=message):
            score.loss(captured, candidates[0], given)
        with pytest.raises(ValueError, match=message):
            score.surface(local, reference, local_given)


def test_surfaces_refuse_kernels_they_cannot_correlate():
    local, reference, variance, _, _ = _placements(torch.float64)
    with pytest.raises(ValueError, match="NMI's surface needs reference_kernel='hard', got 'xu'"):
        NMI(reference_kernel="xu").surface(local, reference)
    with pytest.raises(ValueError, match="ENMI's surface needs reference_kernel='hard', got 'xu'"):
        ENMI(reference_kernel="xu").surface(local, reference, variance)


def test_a_log_prior_per_sample_gives_each_sample_its_row():
    priors = torch.stack([_prior(12), _prior(12).flip(0)])
    score = ENMI(bins=12, log_prior=priors)
    rows = score.per_sample(2)
    assert rows[0] == ENMI(bins=12, log_prior=priors[0]) and rows[1] == ENMI(bins=12, log_prior=priors[1])
    assert ENMI(bins=12, log_prior=priors[0]).per_sample(3)[2] == ENMI(bins=12, log_prior=priors[0])
    assert NCC().per_sample(2) == [NCC(), NCC()]
    with pytest.raises(ValueError, match=r"log_prior must have shape \(12,\), \(1, 12\) or \(3, 12\)"):
        score.per_sample(3)
    # The surface of the batch equals each sample's surface with its own row.
    local, reference, variance, captured_mask, _ = _placements(torch.float64)
    batched = score.surface(local, reference, variance, captured_mask=captured_mask)
    for sample in range(2):
        alone = rows[sample].surface(
            local[sample : sample + 1],
            reference,
            variance[sample : sample + 1],
            captured_mask=captured_mask[sample : sample + 1],
        )
        torch.testing.assert_close(batched.score[sample], alone.score[0], rtol=0, atol=1e-12)


def test_ncc_is_numpy_corrcoef_over_the_valid_pixels(dtype, tolerance):
    captured, candidates, _, valid = _pairs(dtype)
    result = ncc(captured, candidates, valid_mask=valid)
    assert result.shape == (2, 2) and result.dtype == dtype
    for candidate in range(2):
        for sample in range(2):
            keep = valid[sample].numpy().ravel()
            first = captured[sample].double().numpy().ravel()[keep]
            second = candidates[candidate, sample].double().numpy().ravel()[keep]
            expected = np.corrcoef(first, second)[0, 1]
            assert result[candidate, sample].item() == pytest.approx(
                expected, rel=tolerance["rtol"], abs=tolerance["atol"]
            )
    # The roles do not matter, a positive affine change of either side does not either; too few pixels score 0.
    torch.testing.assert_close(ncc(candidates[0], captured, valid_mask=valid), result[0], **tolerance)
    torch.testing.assert_close(ncc(captured * 3 + 7, candidates[0], valid_mask=valid), result[0], **tolerance)
    one = torch.zeros_like(valid)
    one[..., 2, 3] = True
    assert torch.equal(ncc(captured, candidates[0], valid_mask=one), torch.zeros(2, dtype=dtype))
    constant = torch.full_like(captured, 5.0)
    assert torch.equal(ncc(constant, candidates[0]), torch.zeros(2, dtype=dtype))


def test_ncc_has_a_gradient():
    captured, candidates, _, valid = _pairs(torch.float64)
    captured = captured.requires_grad_()
    assert torch.autograd.gradcheck(lambda image: ncc(image, candidates[0], valid_mask=valid), (captured,))
    assert torch.autograd.gradcheck(lambda image: ncc_loss(image, candidates[0], reduction="sum"), (captured,))


def test_ncc_loss_is_one_minus_ncc_zero_for_a_match_and_two_for_an_inverted_one():
    captured, candidates, _, valid = _pairs(torch.float64)
    reference = candidates[0]
    expected = 1 - ncc(captured, reference, valid_mask=valid)
    torch.testing.assert_close(ncc_loss(captured, reference, valid_mask=valid, reduction="none"), expected)
    assert ncc_loss(captured, 3 * captured + 1).abs().max() < 1e-12
    torch.testing.assert_close(
        ncc_loss(captured, -captured, reduction="sum"), torch.tensor(2.0 * len(captured)).double()
    )


def test_score_loss_is_the_score_loss_with_a_variance_model_and_buffers():
    captured, candidates, _, valid = _pairs(torch.float64)
    reference = candidates[0]
    for score in (ECR(bins=12), ENMI(bins=12, kernel="density"), NMI(bins=12, kernel="xu"), NCC(), Mixture(bins=6)):
        given = 40.0 if score.uses_variance else None
        loss = ScoreLoss(score, reduction="none")
        assert torch.equal(
            loss(captured, reference, given, valid_mask=valid),
            score.loss(captured, reference, given, valid_mask=valid, reduction="none"),
        )
    modelled = ScoreLoss("ecr", variance_model=ConstantVariance(40.0))
    assert torch.equal(modelled(captured, reference), ECR().loss(captured, reference, 40.0))
    with pytest.raises(ValueError, match="variance_model is only used by scores that use a variance"):
        ScoreLoss(NCC(), variance_model=ConstantVariance(1.0))
    # A tensor option is a non-persistent buffer that follows the module's dtype, and so does the score.
    prior = ENMILoss(bins=12, log_prior=_prior(12, torch.float32))
    assert "log_prior" not in prior.state_dict() and prior.score.log_prior.dtype == torch.float32
    prior.double()
    assert prior.log_prior.dtype == torch.float64 and prior.score.log_prior.dtype == torch.float64


def test_family_losses_build_their_score_or_take_one():
    assert NMILoss().score == NMI() == NMI(kernel="triangular")  # NMI's one default carries a gradient
    assert NMILoss(NMI(kernel="xu")).score == NMI(kernel="xu")
    assert ENMILoss(kernel="density", bins=8).score == ENMI(kernel="density", bins=8)
    assert ECRLoss(response="linear").score == ECR(response="linear") and MixtureLoss(em_steps=2).score == Mixture(
        em_steps=2
    )
    with pytest.raises(TypeError, match="ENMILoss takes a score or its options, not both"):
        ENMILoss(ENMI(), bins=8)
    with pytest.raises(TypeError, match=r"ECRLoss needs a score of the family ECR, got ENMI\("):
        ECRLoss(ENMI())
    assert isinstance(ENMILoss(), ScoreLoss) and isinstance(ENMILoss().score, Score)


@pytest.mark.parametrize("score", [ENMI(bins=16), NMI(bins=16), Mixture(bins=16)], ids=["enmi", "nmi", "mixture"])
def test_direct_surface_refuses_an_unresolved_captured_image_as_the_surface_does(score):
    # Sample 1 varies inside one bin of the default range (values in [0, 1]): the whole image is checked first, so
    # both name sample 1 (one placement at a time would name its own sample 0).
    local, reference, variance, _, _ = _placements(torch.float64)
    local = local.clone()
    local[1] = torch.linspace(0.0, 1.0, 54, dtype=torch.float64).reshape(1, 6, 9)
    given = variance if score.uses_variance else None
    for surface in (score.surface, lambda *arguments: direct_surface(score, *arguments)):
        with pytest.raises(ValueError, match=r"captured varies \(0 to 1 in sample 1\) but all its valid pixels fall"):
            surface(local, reference, given)


def test_ncc_of_two_valid_pixels_is_plus_or_minus_one_on_the_surface_and_off_it():
    captured = torch.tensor([[[[10.0, 30.0], [20.0, 50.0]]]], dtype=torch.float64)
    reference = torch.tensor([[[[1.0, 9.0, 4.0], [7.0, 2.0, 8.0]]]], dtype=torch.float64)
    reference_mask = torch.tensor([[[[True, False, False], [False, True, True]]]])
    # Placement (0, 0) keeps captured pixels (0, 0) and (1, 1): 10 -> 1 and 50 -> 2, a rising pair; placement (0, 1)
    # keeps (1, 0) and (1, 1): 20 -> 2 and 50 -> 8, rising too.
    fast = NCC().surface(captured, reference, reference_mask=reference_mask)
    slow = direct_surface(NCC(), captured, reference, reference_mask=reference_mask)
    assert fast.overlap.tolist() == [[[2.0, 2.0]]]
    torch.testing.assert_close(fast.score, torch.ones(1, 1, 2, dtype=torch.float64), rtol=0, atol=1e-12)
    torch.testing.assert_close(slow.score, fast.score, rtol=0, atol=1e-12)
    two = torch.tensor([[True, False], [False, True]])
    assert ncc(captured, -reference[..., :2], valid_mask=two).item() == pytest.approx(-1.0)


def test_reliability_weighted_enmi_scores_a_constant_overlap_as_unrelated_images():
    # At placements (u, 10) the captured image's left half, whose values vary inside one bin (their likelihoods spill
    # about 1e-8 into the next one), lies on constant map cells and its right half on unmapped ones: a joint histogram
    # in one cell but for far less than a pixel's weight, scored 1. The masked top row weighs 0, so "less than a
    # pixel's weight" must be measured against the smallest weight of the valid pixels.
    generator = torch.Generator().manual_seed(2)
    window = torch.rand(1, 1, 40, 40, generator=generator, dtype=torch.float64) * 256
    window[..., 10:20] = 100.0
    reference_mask = torch.ones(1, 1, 40, 40, dtype=torch.bool)
    reference_mask[..., 20:] = False
    local = torch.rand(1, 1, 20, 20, generator=generator, dtype=torch.float64) * 256
    local[..., :10] = 100 + 5 * torch.rand(1, 1, 20, 10, generator=generator, dtype=torch.float64)
    captured_mask = torch.ones(1, 1, 20, 20, dtype=torch.bool)
    captured_mask[..., 0, :] = False
    masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
    surface = ENMI(bins=16, reliability=True).surface(local, window, 0.5, **masks)
    assert bool((surface.overlap[0, :, 10] == 19 * 10).all())
    assert bool((surface.score[0, :, 10] == 1.0).all())
