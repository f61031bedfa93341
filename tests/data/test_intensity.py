import numpy as np
import pytest
import torch

from enmi_torch.data import match_intensity


def test_equals_numpy_least_squares_per_pair(dtype, generator):
    prior = torch.rand(3, 1, 6, 7, generator=generator, dtype=dtype) * 200
    local = 1.3 * prior - 12 + torch.randn(3, 1, 6, 7, generator=generator, dtype=dtype) * 5
    valid = torch.rand(3, 1, 6, 7, generator=generator) > 0.3
    local = torch.where(valid, local, torch.nan)  # masked pixels may hold NaN
    fitted = match_intensity(local, prior, valid)
    assert fitted.dtype == dtype and fitted.shape == prior.shape
    for pair in range(3):
        keep = valid[pair].numpy()
        gain, offset = np.polyfit(prior[pair].numpy()[keep].astype(np.float64), local[pair].numpy()[keep], 1)
        np.testing.assert_allclose(fitted[pair].numpy(), gain * prior[pair].numpy() + offset, rtol=1e-5, atol=1e-3)


def test_constant_prior_gets_the_mean_shift():
    prior = torch.full((1, 4), 10.0)
    local = torch.tensor([[11.0, 13.0, 12.0, 12.0]])
    torch.testing.assert_close(match_intensity(local, prior), torch.full((1, 4), 12.0))


@pytest.mark.parametrize(
    ("call", "error", "match"),
    [
        (
            lambda: match_intensity(torch.zeros(2, 4), torch.zeros(2, 5)),
            ValueError,
            r"reference must have the shape of captured \(2, 4\)",
        ),
        (lambda: match_intensity(torch.zeros(2, 4, dtype=torch.int64), torch.zeros(2, 4)), TypeError, "captured"),
        (lambda: match_intensity(torch.zeros(2, 4), torch.zeros(2, 4, dtype=torch.int64)), TypeError, "reference"),
        (lambda: match_intensity(torch.zeros(2, 4), torch.zeros(2, 4), torch.ones(2, 4)), TypeError, "bool"),
    ],
)
def test_invalid_inputs(call, error, match):
    with pytest.raises(error, match=match):
        call()
