"""ncc in float32: a wild pixel whose square overflows float32 scores as in float64."""

import torch

from enmi_torch.functional import ncc


def test_float32_ncc_of_a_wild_pixel_equals_float64():
    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
    captured = reference + 3 * torch.randn(1, 1, 16, 16, generator=generator)
    captured[..., 3, 3] = 1e30  # the squares overflowed float32: the score came out 0, float64 says 0.114
    expected = ncc(captured.double(), reference.double())
    assert 0.05 < float(expected) < 0.5
    torch.testing.assert_close(ncc(captured, reference), expected.float())
