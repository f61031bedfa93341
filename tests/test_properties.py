"""Property-based tests (hypothesis) of the invariants the scores promise, over shapes, dtypes, ranges and variances.

Derandomized (the same examples on every run, CI included), 25 examples a property, images at most 12 x 12.
"""

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from enmi_torch.functional import ecr, enmi, ncc, nmi
from enmi_torch.scores import as_score

# The same 25 examples a property on every run (CI included), no example database.
PROPERTY = settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    database=None,  # nothing written to .hypothesis/
    suppress_health_check=[HealthCheck.too_slow],
)

SCORES = ("ecr", "enmi", "nmi", "ncc")
BINNED = ("ecr", "enmi", "nmi")
USES_VARIANCE = ("ecr", "enmi")
DIFFERENTIABLE = ("ecr", "enmi", "nmi", "ncc")  # every default carries a gradient (NMI's triangular window)


@st.composite
def pairs(draw, max_batch=3):
    """Captured, reference (``(B, 1, H, W)``, spread over the value range), per-pixel variance, the range."""
    batch = draw(st.integers(1, max_batch))
    height, width = draw(st.integers(2, 12)), draw(st.integers(2, 12))
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    low = draw(st.sampled_from([0.0, -50.0, 1000.0]))
    span = draw(st.sampled_from([1.0, 256.0, 4096.0]))
    # Variances from far below a bin (the likelihood a unit count) to several bins wide, in the range's units.
    log_variance = draw(st.tuples(st.floats(-8.0, 0.0), st.floats(0.0, 1.0)))
    seed = draw(st.integers(0, 2**31 - 1))
    generator = torch.Generator().manual_seed(seed)
    shape = (batch, 1, height, width)
    reference = low + span * torch.rand(shape, generator=generator, dtype=torch.float64)
    captured = reference + 0.1 * span * torch.randn(shape, generator=generator, dtype=torch.float64)
    captured = captured.clamp(low, low + span)
    flat = captured.view(batch, -1)
    flat[:, 0], flat[:, -1] = low + 0.05 * span, low + 0.95 * span  # every image spans several bins
    exponent = log_variance[0] + log_variance[1] * torch.rand(shape, generator=generator, dtype=torch.float64)
    variance = (span**2 / 1024) * 10.0**exponent
    value_range = (low, low + span)
    return captured.to(dtype), reference.to(dtype), variance.to(dtype), value_range


def score_of(name, captured, reference, variance, value_range):
    """The functional form of ``name`` with the pair's value range."""
    if name == "ecr":
        return ecr(captured, reference, variance, value_range=value_range)
    if name == "enmi":
        return enmi(captured, reference, variance, value_range=value_range)
    if name == "nmi":
        return nmi(captured, reference, value_range=value_range)
    return ncc(captured, reference)


def tolerance(dtype):
    return {"rtol": 1e-4, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-9, "atol": 1e-10}


@pytest.mark.parametrize("name", SCORES)
@PROPERTY
@given(pair=pairs())
def test_values_and_gradients_are_finite(name, pair):
    captured, reference, variance, value_range = pair
    captured = captured.clone().requires_grad_(name in DIFFERENTIABLE)
    variance = variance.clone().requires_grad_(name in USES_VARIANCE)
    value = score_of(name, captured, reference, variance, value_range)
    assert value.shape == (captured.shape[0],) and value.dtype == captured.dtype
    assert torch.isfinite(value).all(), value
    if name not in DIFFERENTIABLE:
        return
    value.sum().backward()
    assert torch.isfinite(captured.grad).all()
    if name in USES_VARIANCE:
        assert torch.isfinite(variance.grad).all()


@pytest.mark.parametrize("name", SCORES)
@PROPERTY
@given(pair=pairs())
def test_a_batch_scores_as_its_samples_one_by_one(name, pair):
    captured, reference, variance, value_range = pair
    together = score_of(name, captured, reference, variance, value_range)
    alone = torch.cat(
        [
            score_of(name, captured[i : i + 1], reference[i : i + 1], variance[i : i + 1], value_range)
            for i in range(captured.shape[0])
        ]
    )
    torch.testing.assert_close(together, alone, **tolerance(captured.dtype))


@pytest.mark.parametrize("name", SCORES)
@PROPERTY
@given(pair=pairs(), order_seed=st.integers(0, 2**31 - 1))
def test_permuting_pixels_with_their_variances_changes_nothing(name, pair, order_seed):
    captured, reference, variance, value_range = pair
    batch = captured.shape[0]
    captured, reference, variance = (tensor.reshape(batch, 1, -1) for tensor in (captured, reference, variance))
    order = torch.randperm(captured.shape[-1], generator=torch.Generator().manual_seed(order_seed))
    before = score_of(name, captured, reference, variance, value_range)
    after = score_of(name, captured[..., order], reference[..., order], variance[..., order], value_range)
    torch.testing.assert_close(after, before, **tolerance(captured.dtype))


@pytest.mark.parametrize("name", SCORES)
@PROPERTY
@given(pair=pairs())
def test_the_score_objects_equal_the_functions(name, pair):
    captured, reference, variance, value_range = pair
    score = as_score(name)
    if name in BINNED:
        score = score.replace(value_range=value_range)
    value = score(captured, reference, variance if score.uses_variance else None)
    torch.testing.assert_close(value, score_of(name, captured, reference, variance, value_range))


@pytest.mark.parametrize("name", ["enmi", "nmi"])
@PROPERTY
@given(pair=pairs(), scale=st.sampled_from([1e-3, 1e-2, 0.9]))
def test_the_default_range_refuses_images_that_vary_within_one_bin(name, pair, scale):
    # Images in [0, 1) (or narrower) against the default value_range (0, 256): every pixel falls in the first bin.
    captured, reference, variance, value_range = pair
    low, high = value_range

    def squeezed(image):
        return (image - low) / (high - low) * scale

    score = as_score(name)
    with pytest.raises(ValueError, match="value_range"):
        score(
            squeezed(captured),
            squeezed(reference),
            variance * (scale / (high - low)) ** 2 if score.uses_variance else None,
        )


def test_the_default_score_refuses_images_in_0_1_with_the_default_range():
    captured = torch.rand(2, 1, 32, 32, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="value_range"):
        as_score("ecr")(captured, captured, 1e-3)
