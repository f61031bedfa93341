import os
import socket

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from enmi_torch.variance import EmpiricalVariance, empirical_variance


def numpy_paper_variance(local, prior, valid, ddof=1):
    """Var[i, j] = 1 / (n - ddof) sum_k (a_ij^(k) - a~_ij^(k))^2 over the pairs k valid at (i, j), by loops."""
    pairs, height, width = local.shape
    variance = np.full((height, width), np.nan)
    for row in range(height):
        for col in range(width):
            squares = [
                (float(local[k, row, col]) - float(prior[k, row, col])) ** 2 for k in range(pairs) if valid[k, row, col]
            ]
            if len(squares) > ddof:
                variance[row, col] = sum(squares) / (len(squares) - ddof)
    return variance


@pytest.fixture
def pairs(dtype, generator):
    local = torch.randn(9, 1, 5, 6, generator=generator, dtype=dtype) * 3 + 100
    prior = torch.randn(9, 1, 5, 6, generator=generator, dtype=dtype) + 100
    valid = torch.rand(9, 1, 5, 6, generator=generator) > 0.3
    valid[:, :, 0, 0] = False  # never observed
    valid[1:, :, 0, 1] = False  # observed once (pair 0): undefined for ddof=1
    valid[0, :, 0, 1] = True
    return local, prior, valid


@pytest.mark.parametrize("ddof", [0, 1])
def test_equals_numpy_formula(pairs, ddof):
    local, prior, valid = pairs
    variance, defined = empirical_variance(local, prior, valid, ddof=ddof)
    expected = numpy_paper_variance(local[:, 0].numpy(), prior[:, 0].numpy(), valid[:, 0].numpy(), ddof)
    np.testing.assert_array_equal(defined.numpy(), np.isfinite(expected))
    np.testing.assert_allclose(variance.numpy(), expected, rtol=1e-6 if local.dtype == torch.float32 else 1e-12)
    assert variance.dtype == torch.float64
    assert not defined[0, 0] and bool(defined[0, 1]) == (ddof == 0)


def test_without_mask_every_pixel_counts(pairs):
    local, prior, _ = pairs
    variance, defined = empirical_variance(local[:, 0], prior[:, 0])
    expected = ((local - prior).double() ** 2).sum(0)[0] / (local.shape[0] - 1)
    assert bool(defined.all())
    torch.testing.assert_close(variance, expected)


def test_masked_pixels_may_hold_nan_and_are_left_out(pairs):
    local, prior, valid = pairs
    poisoned = torch.where(valid, local, torch.nan)
    torch.testing.assert_close(
        empirical_variance(poisoned, prior, valid)[0], empirical_variance(local, prior, valid)[0], equal_nan=True
    )
    with pytest.raises(ValueError, match="captured - reference must be finite"):
        empirical_variance(poisoned, prior)


def test_shared_mask_equals_per_pair_mask(pairs):
    local, prior, valid = pairs
    shared = valid[0, 0]
    torch.testing.assert_close(
        empirical_variance(local, prior, shared)[0],
        empirical_variance(local, prior, shared.expand_as(valid))[0],
        equal_nan=True,
    )


def test_streaming_equals_one_pass(pairs):
    local, prior, valid = pairs
    stream = EmpiricalVariance((5, 6))
    for start in (0, 2, 3, 7):
        stop = {0: 2, 2: 3, 3: 7, 7: 9}[start]
        stream.update(local[start:stop], prior[start:stop], valid[start:stop])
    one_pass = empirical_variance(local, prior, valid)
    torch.testing.assert_close(stream.compute()[0], one_pass[0], equal_nan=True)
    assert torch.equal(stream.compute()[1], one_pass[1])


def test_merge_and_state_dict_equal_one_pass(pairs):
    local, prior, valid = pairs
    first, second = EmpiricalVariance((5, 6)), EmpiricalVariance((5, 6))
    first.update(local[:4], prior[:4], valid[:4])
    second.update(local[4:], prior[4:], valid[4:])
    restored = EmpiricalVariance((5, 6))
    restored.load_state_dict(first.state_dict())
    merged = restored.merge(second)
    torch.testing.assert_close(merged.compute()[0], empirical_variance(local, prior, valid)[0], equal_nan=True)
    merged.reset()
    assert int(merged.count.sum()) == 0 and not bool(merged.compute()[1].any())


def _all_reduce_worker(rank: int, world: int, port: int, local, prior, valid, results) -> None:
    os.environ["MASTER_ADDR"], os.environ["MASTER_PORT"] = "127.0.0.1", str(port)
    torch.distributed.init_process_group("gloo", rank=rank, world_size=world)
    try:
        stream = EmpiricalVariance(tuple(local.shape[-2:]))
        stream.update(local[rank::world], prior[rank::world], valid[rank::world])
        stream.all_reduce()
        results[rank] = stream.compute()[0]
    finally:
        torch.distributed.destroy_process_group()


def test_all_reduce_over_two_processes_equals_one_pass(generator):
    local = torch.randn(10, 1, 4, 5, generator=generator, dtype=torch.float64)
    prior = torch.zeros_like(local)
    valid = torch.rand(10, 1, 4, 5, generator=generator) > 0.2
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    manager = mp.get_context("spawn").Manager()
    results = manager.dict()
    mp.spawn(_all_reduce_worker, args=(2, port, local, prior, valid, results), nprocs=2)
    expected = empirical_variance(local, prior, valid)[0]
    for rank in range(2):
        torch.testing.assert_close(results[rank], expected, equal_nan=True)


def test_module_follows_device_and_dtype_policy(pairs, device):
    local, prior, valid = pairs
    stream = EmpiricalVariance((5, 6)).to(device)
    variance, _ = stream(local.to(device), prior.to(device), valid.to(device))
    assert variance.device.type == device.type and stream.count.dtype == torch.int64


@pytest.mark.parametrize(
    ("call", "error", "match"),
    [
        (
            lambda: empirical_variance(torch.zeros(2, 3, 3, dtype=torch.int64), torch.zeros(2, 3, 3)),
            TypeError,
            "captured",
        ),
        (lambda: empirical_variance(torch.zeros(2, 3, 3), torch.zeros(2, 3, 4)), ValueError, "reference must have"),
        (lambda: empirical_variance(torch.zeros(6), torch.zeros(6)), ValueError, "captured must have shape"),
        (lambda: empirical_variance(torch.zeros(2, 3, 3), torch.zeros(2, 3, 3), torch.ones(3, 3)), TypeError, "bool"),
        (
            lambda: empirical_variance(torch.zeros(2, 3, 3), torch.zeros(2, 3, 3), torch.ones(4, 4, dtype=torch.bool)),
            ValueError,
            "valid_mask must have the spatial shape",
        ),
        (lambda: empirical_variance(torch.zeros(2, 3, 3), torch.zeros(2, 3, 3), ddof=-1), ValueError, "ddof"),
        (lambda: EmpiricalVariance((3, 0)), ValueError, "shape must be"),
        (
            lambda: EmpiricalVariance((3, 3)).update(torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 4, 4)),
            ValueError,
            r"images of shape \(3, 3\)",
        ),
        (lambda: EmpiricalVariance((3, 3)).merge(EmpiricalVariance((3, 3), ddof=0)), ValueError, "ddof"),
        (lambda: EmpiricalVariance((3, 3)).merge("x"), TypeError, "EmpiricalVariance"),
    ],
)
def test_invalid_inputs(call, error, match):
    with pytest.raises(error, match=match):
        call()


def test_a_fully_masked_pair_adds_nothing(generator):
    captured = torch.randn(3, 1, 4, 5, generator=generator, dtype=torch.float64) * 9
    reference = torch.randn(3, 1, 4, 5, generator=generator, dtype=torch.float64)
    valid = torch.ones(3, 1, 4, 5, dtype=torch.bool)
    valid[1] = False  # a pair the sensor saw nothing of
    variance, defined = empirical_variance(captured, reference, valid)
    expected, expected_defined = empirical_variance(captured[[0, 2]], reference[[0, 2]])
    torch.testing.assert_close(variance, expected)
    assert torch.equal(defined, expected_defined)


def test_residuals_whose_squares_overflow_float64_are_refused_not_inf():
    huge = torch.full((2, 1, 2, 2), 1e200, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"sum of squared residuals overflows torch.float64.*rescale both images"):
        empirical_variance(huge, torch.zeros_like(huge))
    variance, _ = empirical_variance(torch.full((2, 1, 2, 2), 1e30), torch.zeros(2, 1, 2, 2))
    assert torch.allclose(variance, torch.full((2, 2), 2e60, dtype=torch.float64))
