import itertools

import pytest
import torch

from enmi_torch import ConstantVariance, ENMILoss, NMILoss, VarianceModel, enmi, gaussian_log_prior, nmi


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
    from enmi_torch import MixtureLoss, mixture_information
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
    from enmi_torch import ECRLoss, MixtureLoss, ecr_loss, enmi_loss, mixture_loss, nmi_loss

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
        nmi_loss(captured, reference, kernel="hard", reduction="none"), 2 - nmi(captured, reference), **tolerance
    )


def test_loss_modules_take_variance_positionally_like_the_functions_and_the_mask_by_keyword(images):
    from enmi_torch import ECRLoss, MixtureLoss

    captured, reference = images
    valid = torch.ones_like(captured, dtype=torch.bool)
    for loss in (ENMILoss(), ECRLoss(), MixtureLoss()):
        assert torch.equal(loss(captured, reference, 50.0), loss(captured, reference, variance=50.0))
        with pytest.raises(TypeError, match="positional"):
            loss(captured, reference, 50.0, valid)
    with pytest.raises(ValueError, match="variance is not used by score 'nmi'; pass variance=None"):
        NMILoss()(captured, reference, valid)


def test_functional_losses_check_the_reduction(images):
    from enmi_torch import ecr_loss, enmi_loss, mixture_loss, nmi_loss

    captured, reference = images
    for call in (
        lambda: nmi_loss(captured, reference, reduction="avg"),
        lambda: enmi_loss(captured, reference, 1.0, reduction="avg"),
        lambda: ecr_loss(captured, reference, 1.0, reduction="avg"),
        lambda: mixture_loss(captured, reference, 1.0, reduction="avg"),
    ):
        with pytest.raises(ValueError, match="reduction must be one of"):
            call()
