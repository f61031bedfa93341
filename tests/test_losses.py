import itertools

import pytest
import torch

from enmi_torch import ConstantVariance, ENMILoss, NMILoss
from enmi_torch.functional import enmi, gaussian_log_prior, nmi
from enmi_torch.variance import VarianceModel


@pytest.fixture
def images(generator, dtype):
    reference = (torch.rand(3, 1, 16, 16, generator=generator, dtype=torch.float64) * 256).to(dtype)
    captured = reference + 10 * torch.randn(3, 1, 16, 16, generator=generator, dtype=torch.float64).to(dtype)
    return captured, reference


class _HalfMaskedVariance(VarianceModel):
    def forward(self, captured):
        return torch.full((1, 1, *captured.shape[-2:]), 30.0, dtype=captured.dtype)

    def valid_mask(self, captured):
        mask = torch.zeros(1, 1, *captured.shape[-2:], dtype=torch.bool)
        mask[..., : captured.shape[-2] // 2, :] = True
        return mask


@pytest.mark.parametrize("reduction", ["none", "mean", "sum"])
def test_enmi_loss_equals_two_minus_the_function(images, reduction, tolerance):
    captured, reference = images
    log_prior = gaussian_log_prior(128, 32, 32, (0, 256), dtype=captured.dtype)
    loss = ENMILoss(kernel="density", log_prior=log_prior, reduction=reduction)(captured, reference, variance=50.0)
    expected = 2 - enmi(captured, reference, 50.0, kernel="density", log_prior=log_prior)
    expected = {"none": expected, "mean": expected.mean(), "sum": expected.sum()}[reduction]
    torch.testing.assert_close(loss, expected, **tolerance)


def test_nmi_loss_equals_two_minus_the_function(images, tolerance):
    captured, reference = images
    loss = NMILoss(kernel="xu", reduction="none")(captured, reference)
    torch.testing.assert_close(loss, 2 - nmi(captured, reference, kernel="xu"), **tolerance)


def test_variance_model_and_its_mask_are_used(images, tolerance):
    captured, reference = images
    model = _HalfMaskedVariance()
    loss = ENMILoss(variance_model=model, reduction="none")(captured, reference)
    top = (slice(None), slice(None), slice(0, 8), slice(None))
    torch.testing.assert_close(loss, 2 - enmi(captured[top], reference[top], 30.0), **tolerance)


def test_variance_is_learned_through_the_loss(images):
    captured, reference = images
    model = ConstantVariance(400.0, learnable=True)
    loss_module = ENMILoss(variance_model=model)
    assert [name for name, _ in loss_module.named_parameters()] == ["variance_model.log_variance"]
    loss_module(captured, reference).backward()
    assert model.log_variance.grad is not None and torch.isfinite(model.log_variance.grad)


def test_loss_falls_as_alignment_improves(camera_image):
    image = torch.from_numpy(camera_image[100:228, 100:240].astype("float64"))
    reference = image[None, None, :, :128]
    losses = [
        ENMILoss()(image[None, None, :, shift : shift + 128], reference, variance=100.0).item() for shift in range(5)
    ]
    assert all(earlier < later for earlier, later in itertools.pairwise(losses)), losses


def test_prior_is_a_non_persistent_buffer():
    module = ENMILoss(log_prior=gaussian_log_prior(128, 32, 32, (0, 256)))
    assert "log_prior" not in module.state_dict()
    assert module.log_prior.dtype == torch.float32
    assert module.double().log_prior.dtype == torch.float64


def test_loss_errors_name_the_argument(images):
    captured, reference = images
    with pytest.raises(ValueError, match="variance must be given per call"):
        ENMILoss()(captured, reference)
    with pytest.raises(ValueError, match="variance must be None when ENMILoss has a variance_model"):
        ENMILoss(variance_model=ConstantVariance(1.0))(captured, reference, variance=1.0)
    with pytest.raises(TypeError, match=r"variance_model must be an enmi_torch\.variance\.VarianceModel"):
        ENMILoss(variance_model=torch.nn.Identity())
    with pytest.raises(ValueError, match=r"reduction must be one of \['none', 'mean', 'sum'\], got 'max'"):
        NMILoss(reduction="max")
    with pytest.raises(ValueError, match="variance must be a finite number > 0"):
        ConstantVariance(0.0)


def test_mixture_loss_agrees_with_the_function_and_trains():
    from enmi_torch.functional import mixture_information
    from enmi_torch.losses import MixtureLoss
    from enmi_torch.variance import ConstantVariance

    generator = torch.Generator().manual_seed(3)
    reference = torch.rand(2, 1, 6, 5, generator=generator, dtype=torch.float64) * 256
    captured = (reference + torch.randn(reference.shape, generator=generator, dtype=torch.float64) * 9).requires_grad_()
    loss = MixtureLoss(bins=6, em_steps=1, reduction="none")
    expected = -mixture_information(captured, reference, 81.0, bins=6, em_steps=1)
    torch.testing.assert_close(loss(captured, reference, variance=81.0), expected)
    torch.testing.assert_close(
        MixtureLoss(bins=6, em_steps=1, variance_model=ConstantVariance(81.0))(captured, reference), expected.mean()
    )
    loss(captured, reference, variance=81.0).sum().backward()
    assert torch.isfinite(captured.grad).all() and captured.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="em_steps must be an int >= 0"):
        MixtureLoss(em_steps=-1)


@pytest.mark.parametrize("reduction", ["none", "mean", "sum"])
def test_functional_losses_equal_the_modules(images, reduction, tolerance):
    from enmi_torch import ECRLoss
    from enmi_torch.functional import ecr_loss, enmi_loss, mixture_loss, nmi_loss
    from enmi_torch.losses import MixtureLoss

    captured, reference = images
    # Asymmetric settings, so that an argument passed to the wrong place shows.
    valid = torch.ones(1, 1, 16, 16, dtype=torch.bool)
    valid[..., :5, :] = False
    variance = torch.linspace(20.0, 90.0, 16, dtype=captured.dtype).reshape(1, 1, 16, 1).expand(1, 1, 16, 16)
    pairs = [
        (
            NMILoss(bins=12, reduction=reduction)(captured, reference, valid_mask=valid),
            nmi_loss(captured, reference, bins=12, valid_mask=valid, reduction=reduction),
        ),
        (
            ENMILoss(bins=12, kernel="density", reduction=reduction)(
                captured, reference, variance=variance, valid_mask=valid
            ),
            enmi_loss(captured, reference, variance, bins=12, kernel="density", valid_mask=valid, reduction=reduction),
        ),
        (
            ECRLoss(bins=12, reduction=reduction)(captured, reference, variance=variance, valid_mask=valid),
            ecr_loss(captured, reference, variance, bins=12, valid_mask=valid, reduction=reduction),
        ),
        (
            MixtureLoss(bins=12, em_steps=1, reduction=reduction)(
                captured, reference, variance=variance, valid_mask=valid
            ),
            mixture_loss(captured, reference, variance, bins=12, em_steps=1, valid_mask=valid, reduction=reduction),
        ),
    ]
    for module_value, function_value in pairs:
        torch.testing.assert_close(module_value, function_value, **tolerance)
    # The losses are the scores turned around: NMI and ENMI as 2 - score, ECR as -score.
    torch.testing.assert_close(
        nmi_loss(captured, reference, reduction="none"), 2 - nmi(captured, reference), **tolerance
    )


def test_loss_modules_take_variance_positionally_like_the_functions_and_the_mask_by_keyword(images):
    from enmi_torch import ECRLoss
    from enmi_torch.losses import MixtureLoss

    captured, reference = images
    valid = torch.ones_like(captured, dtype=torch.bool)
    for loss in (ENMILoss(), ECRLoss(), MixtureLoss()):
        assert torch.equal(loss(captured, reference, 50.0), loss(captured, reference, variance=50.0))
        with pytest.raises(TypeError, match="positional"):
            loss(captured, reference, 50.0, valid)
    with pytest.raises(ValueError, match="variance is not used by score 'nmi'; pass variance=None"):
        NMILoss()(captured, reference, valid)


def test_functional_losses_check_the_reduction(images):
    from enmi_torch.functional import ecr_loss, enmi_loss, mixture_loss, nmi_loss

    captured, reference = images
    for call in (
        lambda: nmi_loss(captured, reference, reduction="avg"),
        lambda: enmi_loss(captured, reference, 1.0, reduction="avg"),
        lambda: ecr_loss(captured, reference, 1.0, reduction="avg"),
        lambda: mixture_loss(captured, reference, 1.0, reduction="avg"),
    ):
        with pytest.raises(ValueError, match="reduction must be one of"):
            call()


def _family_cases():
    from enmi_torch import ECR, ENMI, NCC, NMI, ECRLoss, Mixture
    from enmi_torch.functional import ecr_loss, enmi_loss, mixture_loss, ncc_loss, nmi_loss
    from enmi_torch.losses import MixtureLoss, ScoreLoss

    def module_of(family):
        return lambda reduction, **options: ScoreLoss(family(**options), reduction=reduction)

    # (score class, its options, whether it takes a variance, the functional loss, the family's loss module)
    return {
        "nmi": (NMI, {"bins": 12}, False, nmi_loss, NMILoss),
        "nmi_xu": (NMI, {"bins": 12, "kernel": "xu", "value_range": (-8.0, 264.0)}, False, nmi_loss, NMILoss),
        "enmi": (ENMI, {"bins": 12, "kernel": "density"}, True, enmi_loss, ENMILoss),
        "ecr": (ECR, {"bins": 12, "response": "binned"}, True, ecr_loss, ECRLoss),
        "ecr_default": (ECR, {}, True, ecr_loss, ECRLoss),
        "ncc": (NCC, {}, False, ncc_loss, module_of(NCC)),
        "mixture": (Mixture, {"bins": 12, "em_steps": 1}, True, mixture_loss, MixtureLoss),
    }


@pytest.mark.parametrize("case", list(_family_cases()))
@pytest.mark.parametrize("reduction", ["none", "mean"])
def test_the_four_paths_to_a_loss_are_one_computation(case, reduction):
    from enmi_torch.losses import ScoreLoss

    family, options, uses_variance, function, module = _family_cases()[case]
    generator = torch.Generator().manual_seed(36)
    reference = torch.rand(2, 1, 16, 16, generator=generator, dtype=torch.float64) * 256
    captured = reference + 12 * torch.randn(2, 1, 16, 16, generator=generator, dtype=torch.float64)
    valid = torch.ones(1, 1, 16, 16, dtype=torch.bool)
    valid[..., :3, :] = False
    variance = (
        (torch.linspace(60.0, 200.0, 16, dtype=torch.float64).reshape(1, 1, 16, 1).expand(1, 1, 16, 16),)
        if uses_variance
        else ()
    )
    score = family(**options)
    assert score.is_differentiable and score.higher_is_better
    paths = {
        "function": lambda c: function(c, reference, *variance, valid_mask=valid, reduction=reduction, **options),
        "score.loss": lambda c: score.loss(c, reference, *variance, valid_mask=valid, reduction=reduction),
        "ScoreLoss": lambda c: ScoreLoss(score, reduction=reduction)(c, reference, *variance, valid_mask=valid),
        "module": lambda c: module(reduction=reduction, **options)(c, reference, *variance, valid_mask=valid),
    }
    results = {}
    for name, path in paths.items():
        leaf = captured.clone().requires_grad_()
        value = path(leaf)
        assert value.requires_grad, name
        value.sum().backward()
        assert torch.isfinite(leaf.grad).all() and leaf.grad.abs().sum() > 0, name
        results[name] = (value.detach(), leaf.grad)
    expected_value, expected_grad = results["score.loss"]
    for name, (value, grad) in results.items():
        torch.testing.assert_close(value, expected_value, rtol=0, atol=0, msg=name)
        torch.testing.assert_close(grad, expected_grad, rtol=0, atol=0, msg=name)


def test_the_defaults_are_the_score_s_own():
    # The case: the paths once gave 0.5437 with a gradient and 0.4526 without one.
    from enmi_torch import NMI
    from enmi_torch.functional import nmi_loss
    from enmi_torch.losses import ScoreLoss

    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(2, 1, 16, 16, generator=generator) * 256
    captured = (reference + 20 * torch.randn(2, 1, 16, 16, generator=generator)).requires_grad_()
    values = [
        nmi_loss(captured, reference, bins=8),
        NMI(bins=8).loss(captured, reference),
        ScoreLoss(NMI(bins=8))(captured, reference),
        NMILoss(bins=8)(captured, reference),
    ]
    assert all(value.requires_grad for value in values)
    for value in values[1:]:
        torch.testing.assert_close(value, values[0])
    torch.testing.assert_close(ScoreLoss("nmi")(captured, reference), nmi_loss(captured, reference))
    assert NMILoss().score == NMI() == NMI(kernel="triangular")


def test_a_loss_without_gradient_is_refused_by_name(images):
    from enmi_torch import NMI
    from enmi_torch.functional import nmi_loss
    from enmi_torch.losses import ScoreLoss

    captured, reference = images
    hard = NMI(bins=8, kernel="hard")
    assert not hard.is_differentiable and hard.higher_is_better
    message = r"NMI\(bins=8, .*kernel='hard'.*\) has no gradient: give kernel='triangular'"
    for call in (
        lambda: NMILoss(bins=8, kernel="hard"),
        lambda: ScoreLoss(hard),
        lambda: NMILoss(hard),
        lambda: hard.loss(captured, reference),
        lambda: nmi_loss(captured, reference, bins=8, kernel="hard"),
    ):
        with pytest.raises(ValueError, match=message):
            call()
    # The measurement itself stays available without gradient.
    assert hard(captured, reference).shape == (3,)
