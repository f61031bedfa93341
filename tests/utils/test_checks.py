"""Checks shared by every public function: an empty batch is refused the same way everywhere."""

import pytest
import torch

from enmi_torch import ECR, ENMILoss, NMILoss
from enmi_torch.data import match_intensity
from enmi_torch.functional import (
    ecr,
    enmi,
    enmi_surface,
    joint_histogram,
    mixture_information,
    ncc,
    ncc_surface,
    nmi,
    nmi_from_joint_histogram,
    nmi_surface,
)
from enmi_torch.histogram import hard_entropies
from enmi_torch.localization.search import localize
from enmi_torch.scores import direct_surface
from enmi_torch.variance import EmpiricalVariance, LearnedVariance, empirical_variance, gaussian_nll

EMPTY = torch.zeros(0, 1, 4, 4)
WINDOW = torch.zeros(1, 1, 8, 8)


@pytest.mark.parametrize(
    ("name", "call"),
    [
        ("captured", lambda: nmi(EMPTY, EMPTY)),
        ("captured", lambda: nmi(EMPTY, EMPTY, kernel="triangular")),
        ("captured", lambda: enmi(EMPTY, EMPTY, 1.0)),
        ("captured", lambda: joint_histogram(EMPTY, EMPTY)),
        ("captured", lambda: hard_entropies(EMPTY, EMPTY)),
        ("captured", lambda: NMILoss()(EMPTY, EMPTY)),
        ("captured", lambda: ENMILoss()(EMPTY, EMPTY, variance=1.0)),
        ("captured", lambda: nmi(torch.zeros(2, 1, 0, 4), torch.zeros(2, 1, 0, 4))),
        ("captured", lambda: enmi_surface(EMPTY, WINDOW, 1.0)),
        ("captured", lambda: nmi_surface(EMPTY, WINDOW)),
        ("captured", lambda: ncc_surface(EMPTY, WINDOW)),
        ("captured", lambda: direct_surface("nmi", EMPTY, WINDOW)),
        ("captured", lambda: localize(EMPTY, WINDOW, 1.0, shifts=1)),
        ("residual", lambda: gaussian_nll(EMPTY, torch.zeros(4, 4))),
        ("captured", lambda: LearnedVariance((4, 4)).nll(EMPTY, EMPTY)),
        ("captured", lambda: empirical_variance(EMPTY, EMPTY)),
        ("captured", lambda: EmpiricalVariance((4, 4)).update(EMPTY, EMPTY)),
        ("captured", lambda: match_intensity(EMPTY, EMPTY)),
    ],
)
def test_an_empty_batch_is_refused_the_same_way_everywhere(name, call):
    with pytest.raises(ValueError, match=rf"^{name} must hold at least one sample and one pixel, got shape \("):
        call()


def test_images_in_unit_range_against_the_default_bins_are_refused_everywhere():
    import enmi_torch
    from enmi_torch.functional import enmi_surface, nmi_surface

    unit = torch.rand(2, 1, 12, 10, generator=torch.Generator().manual_seed(0))
    message = r"captured varies .* but all its valid pixels fall in one of the 32 bins of value_range=\(0.0, 256.0\)"
    calls = [
        lambda: enmi_torch.functional.nmi(unit, unit),
        lambda: enmi_torch.functional.enmi(unit, unit, 0.01),
        lambda: enmi_torch.functional.joint_histogram(unit, unit),
        lambda: enmi_torch.NMILoss()(unit, unit),
        lambda: enmi_torch.ENMILoss()(unit, unit, variance=0.01),
        lambda: enmi_torch.functional.mixture_information(unit, unit, 0.01),
    ]
    for call in calls:
        with pytest.raises(ValueError, match=message):
            call()
    local_message = r"captured varies .* all its valid pixels fall in one of the 32 bins"
    for call in (
        lambda: nmi_surface(unit[..., :6, :5], unit),
        lambda: enmi_surface(unit[..., :6, :5], unit, 0.01),
        lambda: enmi_torch.localize(unit[..., :6, :5], unit, 0.01, shifts=1, score="enmi"),
    ):
        with pytest.raises(ValueError, match=local_message):
            call()
    # The right range scores them; a constant image is still a valid (uninformative) input.
    assert enmi_torch.functional.nmi(unit, unit, value_range=(0.0, 1.0), kernel="hard").tolist() == pytest.approx(
        [2.0, 2.0]
    )
    assert enmi_torch.functional.nmi(torch.full_like(unit, 0.5), unit * 255).tolist() == pytest.approx(
        [1.0, 1.0], abs=1e-6
    )
    # ECR models the captured values themselves (any units); only its reference is binned.
    assert torch.isfinite(enmi_torch.functional.ecr(unit, unit * 255, 0.01)).all()


def test_value_checks_switch_turns_value_checks_off_and_on_everywhere():
    import enmi_torch

    unit = torch.rand(1, 1, 6, 6, generator=torch.Generator().manual_seed(1))
    with enmi_torch.value_checks(False):
        assert enmi_torch.functional.nmi(unit, unit).tolist() == [1.0]  # unchecked: the caller's responsibility
    with pytest.raises(ValueError, match="captured varies"):
        enmi_torch.functional.nmi(unit, unit)
    with enmi_torch.value_checks(True), pytest.raises(ValueError, match="captured varies"):
        enmi_torch.functional.nmi(unit, unit)
    with pytest.raises(TypeError, match="enabled must be True, False or None"):
        with enmi_torch.value_checks("off"):
            pass


@pytest.mark.parametrize(
    "call",
    [
        lambda value_range: nmi(WINDOW, WINDOW, value_range=value_range),
        lambda value_range: enmi(WINDOW, WINDOW, 1.0, value_range=value_range),
        lambda value_range: joint_histogram(WINDOW, WINDOW, value_range=value_range),
        lambda value_range: ecr(WINDOW, WINDOW, 1.0, value_range=value_range),
        lambda value_range: mixture_information(WINDOW, WINDOW, 1.0, value_range=value_range),
        lambda value_range: nmi_surface(WINDOW[..., :4, :4], WINDOW, value_range=value_range),
    ],
)
def test_a_value_range_whose_width_overflows_is_refused_by_every_binned_function(call):
    with pytest.raises(ValueError, match=r"value_range must have a finite width .* got \(-1e\+308, 1e\+308\)"):
        call((-1e308, 1e308))


def test_a_switch_takes_a_bool_only_so_a_truthy_string_does_not_switch_it_on():
    # localize(refine='no') refined before: any truthy value was taken (the tracker checked it, localize did not).
    reference = torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(0)) * 255
    captured = reference[..., 8:24, 8:24].clone()
    for refine in ("no", 1, None):
        with pytest.raises(TypeError, match=rf"refine must be a bool \(True or False\), got \w+ {refine!r}"):
            localize(captured, reference, 4.0, shifts=2, refine=refine)


def test_cheap_bins_are_checked_under_their_own_name():
    from enmi_torch import ECR
    from enmi_torch.localization import Localizer, SearchStrategy

    for cheap_bins, error in ((1, ValueError), (2.5, TypeError), (2**25, ValueError)):
        with pytest.raises(error, match="cheap_bins must be"):
            SearchStrategy("two_stage", cheap_bins=cheap_bins)
    with pytest.raises(ValueError, match=r"cheap_bins must be at most bins \(16\), got 32"):
        Localizer(score=ECR(bins=16), search=SearchStrategy("two_stage", cheap_bins=32))
    with pytest.raises(TypeError, match=r"Localizer\(\) takes cheap_bins in search=SearchStrategy"):
        Localizer(score=ECR(bins=16), search="two_stage", cheap_bins=8)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_variance_that_takes_a_gradient_is_refused_where_its_gradient_would_overflow(dtype):
    # ECR weighs each pixel by 1 / variance: its gradient in the variance holds 1 / variance^2. In float32 1e-30 gave
    # 23 NaN and 233 -inf of 256 in variance.grad; float64 holds it.
    generator = torch.Generator().manual_seed(0)
    reference = (torch.rand(1, 1, 16, 16, generator=generator, dtype=torch.float64) * 250).to(dtype)
    captured = reference + torch.randn(1, 1, 16, 16, generator=generator, dtype=torch.float64).to(dtype)
    tiny = torch.full((1, 1, 16, 16), 1e-30, dtype=dtype, requires_grad=True)
    if dtype == torch.float32:
        with pytest.raises(ValueError, match=r"variance must be at least 6\.\d+e-15 in torch.float32 .* got 1e-30"):
            ecr(captured, reference, tiny, model_variance=0.0)
        assert bool(torch.isfinite(ecr(captured, reference, tiny.detach(), model_variance=0.0)).all())  # no gradient
    smallest = torch.full((1, 1, 16, 16), 1e-14 if dtype == torch.float32 else 1e-30, dtype=dtype, requires_grad=True)
    score = ecr(captured, reference, smallest, model_variance=0.0)
    score.sum().backward()
    assert bool(torch.isfinite(score).all()) and bool(torch.isfinite(smallest.grad).all())


@pytest.mark.parametrize(
    ("value", "error", "match"),
    [
        (torch.zeros(3), ValueError, r"pose must have shape \(B, 3\), rows \(x, y, yaw\), got \(3,\)"),
        (torch.zeros(2, 3), ValueError, r"pose must have shape \(1, 3\), rows \(x, y, yaw\), got \(2, 3\)"),
        (torch.zeros(0, 3), ValueError, r"pose must hold at least one row"),
        (torch.zeros(1, 3, dtype=torch.long), TypeError, "pose must be a floating-point tensor, got dtype torch.int64"),
        (torch.zeros(1, 3, dtype=torch.complex64), TypeError, "pose must be a floating-point tensor"),
        (torch.zeros(1, 3, device="meta"), ValueError, "pose must hold data, got a meta tensor"),
        (torch.tensor([[0.0, float("inf"), 0.0]]), ValueError, r"pose must be finite, got NaN or inf in \[\[0.0, inf"),
        ([[0.0, 0.0, 0.0]], TypeError, "pose must be a torch.Tensor, got list"),
    ],
)
def test_a_pose_is_refused_by_name(value, error, match):
    from enmi_torch.utils.checks import check_pose

    batch = 1 if value is not None and getattr(value, "shape", (0,))[0] == 2 else None
    with pytest.raises(error, match=match):
        check_pose("pose", value, batch)


def test_a_margin_and_a_mask_are_refused_by_name():
    from enmi_torch.utils.checks import check_margin, check_mask_of

    assert check_margin("margin", 0) == 0.0 and check_margin("margin", 1.5, positive=True) == 1.5
    for value, error in ((-1.0, ValueError), (float("nan"), ValueError), (float("inf"), ValueError), ("1", TypeError)):
        with pytest.raises(error, match=r"margin must be a finite number >= 0 \(cells from the map's border\)"):
            check_margin("margin", value)
    with pytest.raises(ValueError, match=r"margin must be a finite number > 0 \(the largest move, in cells\), got 0"):
        check_margin("margin", 0, positive=True, meaning="the largest move, in cells")
    like = torch.zeros(2, 1, 5, 7)
    assert check_mask_of("mask", torch.ones(5, 7, dtype=torch.bool), "map", like).shape == (1, 1, 5, 7)
    assert check_mask_of("mask", torch.ones(2, 1, 5, 7, dtype=torch.bool), "map", like).shape == (2, 1, 5, 7)
    for mask in (torch.ones(1, 1, 7, 5), torch.ones(3, 1, 5, 7), torch.ones(1, 1, 4, 7), torch.ones(5, 7, 1)):
        with pytest.raises(ValueError, match=r"mask must be as large as map, \(1, 1, 5, 7\) or \(2, 1, 5, 7\) or"):
            check_mask_of("mask", mask.bool(), "map", like)
    with pytest.raises(TypeError, match=r"mask must be a bool tensor, got dtype torch\.float32"):
        check_mask_of("mask", torch.ones(1, 1, 5, 7), "map", like)


IMAGE = torch.rand(64, 64, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 255


@pytest.mark.parametrize(
    "call",
    [
        lambda image: nmi(image, image),
        lambda image: enmi(image, image, 1.0),
        lambda image: ecr(image, image, 1.0),
        lambda image: mixture_information(image, image, 1.0),
        lambda image: joint_histogram(image, image),
        lambda image: hard_entropies(image, image),
        lambda image: NMILoss()(image, image),
        lambda image: ENMILoss()(image, image, variance=1.0),
    ],
)
def test_a_2d_tensor_is_refused_naming_both_readings_not_scored_per_row(call):
    # nmi(captured[0, 0], reference[0, 0]) on a (64, 64) image returned 64 per-row scores before.
    with pytest.raises(ValueError, match=r"captured must have shape \(B, 1, H, W\) or \(B, H, W\), got the 2-D shape"):
        call(IMAGE)
    with pytest.raises(ValueError, match=r"one \(H, W\) image or \(B, N\) flat samples: pass one image as"):
        call(IMAGE)


def test_flat_samples_are_one_row_of_pixels_each_and_take_their_maps_flat():
    from enmi_torch.functional import ncc

    generator = torch.Generator().manual_seed(4)
    captured = torch.rand(3, 1, 40, generator=generator, dtype=torch.float64) * 255
    reference = captured + 20 * torch.randn(3, 1, 40, generator=generator, dtype=torch.float64)
    variance = torch.rand(3, 40, generator=generator, dtype=torch.float64) + 0.5
    as_images = [score(captured[:, None], reference[:, None]) for score in (nmi, ncc)]
    assert [score(captured, reference).tolist() for score in (nmi, ncc)] == [value.tolist() for value in as_images]
    per_sample = enmi(captured, reference, variance)  # (B, N) beside flat samples (B, 1, N): one row per sample
    torch.testing.assert_close(per_sample, enmi(captured, reference, variance[:, None]))
    shared = enmi(captured, reference, variance[0])  # (N,): one map for every sample
    torch.testing.assert_close(shared, enmi(captured, reference, variance[:1, None].expand(3, 1, 40)))
    with pytest.raises(ValueError, match=r"variance must have the spatial shape of captured \(1, 40\)"):
        enmi(captured, reference, variance[:2])


def test_the_far_outside_range_rule_counts_valid_pixels_only_and_strictly_beyond_eight_widths():
    from enmi_torch.utils.checks import check_resolved_by_bins

    value_range = (0.0, 2.0)  # eight widths below 0 is -16
    inside = torch.linspace(0.0, 2.0, 10, dtype=torch.float64).repeat(1, 10)  # (1, 100)
    first = torch.arange(100)[None]

    def with_far(count: int, value: float = -16.5) -> torch.Tensor:
        return torch.where(first < count, value, inside)

    check_resolved_by_bins("captured", with_far(60, -16.0), None, 8, value_range)  # exactly eight widths: not beyond
    with pytest.raises(
        ValueError, match=r"captured lies far outside value_range=\(0.0, 2.0\): 60% of its valid pixels"
    ):
        check_resolved_by_bins("captured", with_far(60), None, 8, value_range)
    check_resolved_by_bins("captured", with_far(40), None, 8, value_range)  # 40 %: noise spilling over
    valid = first >= 60  # the far pixels masked out
    check_resolved_by_bins("captured", with_far(60), valid, 8, value_range)
    valid = (first >= 50) & (first < 70)  # 10 far of 20 valid: half is not more than half
    check_resolved_by_bins("captured", with_far(60), valid, 8, value_range)
    valid = (first >= 49) & (first < 70)  # 11 of 21
    with pytest.raises(ValueError, match=r"52% of its valid pixels in sample 0"):
        check_resolved_by_bins("captured", with_far(60), valid, 8, value_range)


def test_the_number_checks_hold_at_their_edges():
    from enmi_torch.utils.checks import (
        check_bins,
        check_captured_in_reference,
        check_counts,
        check_positive_number,
        check_positive_where,
        check_value_range,
        check_variance_fits,
    )

    with pytest.raises(ValueError, match="x must be a finite number > 0, got 0"):
        check_positive_number("x", 0)
    assert check_bins(2) == 2
    with pytest.raises(ValueError, match=r"value_range must be finite with low < high, got \(1.0, 1.0\)"):
        check_value_range((1.0, 1.0))
    tiny, largest = torch.finfo(torch.float32).tiny, torch.finfo(torch.float32).max / 1e3
    check_variance_fits("variance", tiny, torch.float32)  # the edges themselves fit
    check_variance_fits("variance", largest, torch.float32)
    check_variance_fits("variance", 0.0, torch.float32)  # not positive: left to the positivity check
    check_variance_fits("variance", torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64), torch.float32)
    with pytest.raises(ValueError, match=r"variance must lie within 1.18e-38 to 3.4e\+35 to be held in torch.float32"):
        check_variance_fits("variance", 1e37, torch.float32)
    with pytest.raises(ValueError, match=r"got 1e-39"):
        check_variance_fits("variance", torch.tensor([1e-39, 1.0], dtype=torch.float64), torch.float32)
    with pytest.raises(ValueError, match=r"variance must be finite and > 0 where valid_mask is True, got 1 value"):
        check_positive_where("variance", torch.tensor([[1.0, -1.0]]), None)
    with pytest.raises(ValueError, match=r"counts must be finite counts >= 0, got 1 value\(s\) outside"):
        check_counts("counts", torch.tensor([1.0, -1.0]))
    assert check_captured_in_reference(torch.zeros(1, 1, 4, 6), torch.zeros(1, 1, 4, 6), "H, W") == (1, 4, 6)


def _scene():
    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(1, 1, 48, 48, generator=generator) * 256
    return reference[..., 14:30, 19:35].clone(), reference


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda x: nmi(x, x.to("meta")), "reference must hold data, got a meta tensor"),
        (lambda x: nmi(x.to("meta"), x.to("meta")), "captured must hold data, got a meta tensor"),
        (lambda x: enmi(x, x.to("meta"), variance=4.0), "reference must hold data, got a meta tensor"),
        (lambda x: enmi(x, x, variance=torch.ones_like(x, device="meta")), "variance must hold data"),
        (lambda x: localize(x[..., :8, :8], x.to("meta"), 64.0, shifts=2), "reference must hold data"),
        (lambda x: ecr(x, x.to("meta"), 4.0), "reference must hold data, got a meta tensor"),
        (lambda x: ecr(x, x, torch.ones_like(x, device="meta")), "variance must hold data"),
        (lambda x: ncc(x, x.to("meta")), "reference must hold data, got a meta tensor"),
        # The surfaces over every placement, the direct loop and the search's variance and masks (issue 43).
        (lambda x: ECR().surface(x[..., :8, :8].to("meta"), x.to("meta"), 4.0), "captured must hold data"),
        (lambda x: ECR().surface(x[..., :8, :8], x.to("meta"), 4.0), "reference must hold data"),
        (lambda x: ECR().surface(x[..., :8, :8], x, torch.ones(8, 8, device="meta")), "variance must hold data"),
        (lambda x: direct_surface(ECR(), x[..., :8, :8].to("meta"), x.to("meta"), 4.0), "captured must hold data"),
        (lambda x: direct_surface("ncc", x[..., :8, :8], x.to("meta")), "reference must hold data"),
        (lambda x: localize(x[..., :8, :8].to("meta"), x, 64.0, shifts=2), "captured must hold data"),
        (lambda x: localize(x[..., :8, :8], x, torch.ones(8, 8, device="meta"), shifts=2), "variance must hold data"),
        (
            lambda x: localize(
                x[..., :8, :8], x, 64.0, shifts=2, captured_mask=torch.ones(8, 8, dtype=bool, device="meta")
            ),
            "captured_mask must hold data",
        ),
        (
            lambda x: localize(
                x[..., :8, :8], x, 64.0, shifts=2, reference_mask=torch.ones(16, 16, dtype=bool, device="meta")
            ),
            "reference_mask must hold data",
        ),
        (
            lambda x: ecr(x, x, 4.0, valid_mask=torch.ones(16, 16, dtype=bool, device="meta")),
            "valid_mask must hold data",
        ),
    ],
)
def test_a_tensor_without_data_on_the_device_is_named(call, message):
    with pytest.raises(ValueError, match=rf"^{message}") as refusal:
        call(torch.rand(1, 1, 16, 16) * 255)
    assert "got a meta tensor (a shape only) of shape (" in str(refusal.value) and "\n" not in str(refusal.value)


def test_a_log_prior_that_rules_out_every_bin_is_refused():
    x = torch.rand(1, 1, 16, 16, generator=torch.Generator().manual_seed(0)) * 255
    with pytest.raises(ValueError, match="log_prior must allow at least one bin"):
        enmi(x, x + 1, variance=4.0, log_prior=torch.full((32,), -torch.inf))


@pytest.mark.parametrize("count", [float("nan"), -0.5, float("inf")])
def test_nmi_from_a_histogram_of_bad_counts_is_refused(count):
    counts = torch.ones(1, 4, 4)
    counts[0, 0, 0] = count
    with pytest.raises(ValueError, match="counts must be finite counts >= 0"):
        nmi_from_joint_histogram(counts)


@pytest.mark.parametrize(
    "call",
    [
        lambda x, r: nmi(x, r, value_range=(0.0, 1.0)),
        lambda x, r: enmi(x, r, variance=4.0, value_range=(0.0, 1.0)),
        lambda x, r: ecr(x, r, 4.0, value_range=(0.0, 1.0)),
    ],
)
def test_images_mostly_far_outside_value_range_are_refused(call):
    # 0-255 images against value_range=(0, 1), with a few pixels below 1 so that not all fall in one bin: the score
    # of the few pixels inside was returned (nmi gave 1.0006).
    generator = torch.Generator().manual_seed(3)
    captured = torch.rand(1, 1, 24, 20, generator=generator) * 255
    captured[..., :2, :] = torch.rand(1, 1, 2, 20, generator=generator)
    far = r"lies far outside value_range=\(0\.0, 1\.0\): [89]\d% of its valid pixels .* more than 8 range widths"
    with pytest.raises(
        ValueError,
        match=far,
    ):
        call(captured, captured.flip(-1))


def test_noise_spilling_past_value_range_is_still_scored():
    generator = torch.Generator().manual_seed(4)
    reference = torch.rand(1, 1, 24, 20, generator=generator, dtype=torch.float64) * 256
    # std 640: the paper's simulation at its largest noise power, on its farthest tiles
    captured = reference + 640.0 * torch.randn(reference.shape, generator=generator, dtype=torch.float64)
    assert ((captured < 0) | (captured > 256)).double().mean() > 0.7
    assert torch.isfinite(nmi(captured, reference)).all()


def test_float32_surfaces_refuse_values_whose_squares_overflow_and_float64_scores_them():
    from enmi_torch.functional import ecr_surface

    captured, reference = _scene()
    captured[..., 3, 3] = 1e30  # one wild pixel: float32 squares overflowed into a NaN surface
    with pytest.raises(ValueError, match=r"captured holds 1 value\(s\) beyond \+-1e\+18 where captured_mask is True"):
        ecr_surface(captured, reference, 4.0, bins=16)
    with pytest.raises(ValueError, match=r"captured holds 1 value\(s\) beyond"):  # was 'no candidate passes'
        localize(captured, reference, 4.0, score=ECR(bins=16), shifts=3)
    surface = ecr_surface(captured.double(), reference.double(), 4.0, bins=16)
    assert torch.isfinite(surface.score).all()


@pytest.mark.parametrize(("scale", "variance", "shown"), [(1e-20, 4.0, "4e-40"), (1e19, 4.0, r"4e\+38")])
def test_a_variance_float32_cannot_hold_is_refused_and_float64_scores_it(scale, variance, shown):
    from enmi_torch.functional import ecr_surface

    captured, reference = _scene()
    captured, reference = (captured * scale).double(), (reference * scale).double()
    options = {"bins": 16, "value_range": (0.0, 256 * scale)}
    wide = ecr_surface(captured, reference, variance * scale**2, **options)
    assert torch.isfinite(wide.score).all() and divmod(int(wide.score[0].argmax()), 33) == (14, 19)
    for given in (variance * scale**2, torch.full_like(captured, variance * scale**2)):
        with pytest.raises(ValueError, match=rf"variance must lie within 1.18e-38 to 3.4e\+35 .* got {shown}"):
            enmi(captured.float(), captured.float(), variance=given, value_range=options["value_range"])
