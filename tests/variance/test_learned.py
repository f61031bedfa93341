import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from _pickle_payload import EXECUTED, Payload

from enmi_torch import ENMILoss
from enmi_torch.data import SyntheticPairs, camera_truth, lidar_truth
from enmi_torch.functional import enmi
from enmi_torch.utils.budget import MemoryBudgetError, memory_budget
from enmi_torch.variance import (
    LearnedVariance,
    empirical_variance,
    gaussian_nll,
    perspective_basis,
    radial_basis,
    smoothness_penalty,
)


def relative_rms(estimate, reference, valid):
    return float(((estimate[valid] / reference[valid] - 1) ** 2).mean().sqrt())


def fit(model, local, prior, valid, steps=400, lr=0.05):
    """Full-batch Adam on the model's objective (NLL per pair and pixel, plus the prior's share)."""
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps)
    scale = local.shape[0] * local.shape[-2] * local.shape[-1]
    for _ in range(steps):
        loss = (model.nll(local, prior, valid, reduction="sum") + model.penalty()) / scale
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
    return model


def stack(pairs, count):
    items = [pairs[index] for index in range(count)]
    return tuple(torch.stack([item[key] for item in items]) for key in ("local", "prior", "valid"))


# ----- gaussian_nll ------------------------------------------------------------------------------------------------
def test_gaussian_nll_equals_torch_reference(dtype, generator, tolerance):
    residual = torch.randn(3, 1, 4, 5, generator=generator, dtype=dtype) * 2
    log_variance = torch.randn(4, 5, generator=generator, dtype=dtype)
    expected = F.gaussian_nll_loss(
        torch.zeros_like(residual), residual, log_variance.exp().expand_as(residual), full=True, eps=0.0
    )
    torch.testing.assert_close(gaussian_nll(residual, log_variance), expected, **tolerance)
    per_pixel = gaussian_nll(residual, log_variance, reduction="none")
    assert per_pixel.shape == (3, 20)
    torch.testing.assert_close(per_pixel.sum(), gaussian_nll(residual, log_variance, reduction="sum"), **tolerance)


def test_gaussian_nll_masked_equals_selected(dtype, generator, tolerance):
    residual = torch.randn(2, 1, 4, 4, generator=generator, dtype=dtype)
    log_variance = torch.randn(4, 4, generator=generator, dtype=dtype)
    valid = torch.rand(2, 1, 4, 4, generator=generator) > 0.4
    selected, log_selected = residual[valid], log_variance.expand(2, 1, 4, 4)[valid]
    expected = 0.5 * (selected**2 / log_selected.exp() + log_selected + math.log(2 * math.pi)).mean()
    torch.testing.assert_close(gaussian_nll(residual, log_variance, valid), expected, **tolerance)


def test_gaussian_nll_gradcheck(generator):
    residual = torch.randn(2, 1, 3, 3, generator=generator, dtype=torch.float64, requires_grad=True)
    log_variance = torch.randn(3, 3, generator=generator, dtype=torch.float64, requires_grad=True)
    valid = torch.rand(2, 1, 3, 3, generator=generator) > 0.3
    assert torch.autograd.gradcheck(lambda r, s: gaussian_nll(r, s, valid), (residual, log_variance))


def test_masked_nan_pixels_get_no_gradient(generator):
    residual = torch.randn(2, 1, 3, 3, generator=generator)
    valid = torch.ones(2, 1, 3, 3, dtype=torch.bool)
    valid[:, :, 0, 0] = False
    residual[:, :, 0, 0] = torch.nan
    log_variance = torch.zeros(3, 3, requires_grad=True)
    log_map = torch.where(valid[0, 0], log_variance, torch.nan)  # the map may be undefined where unused too
    gaussian_nll(residual, log_map, valid).backward()
    assert torch.isfinite(log_variance.grad).all() and log_variance.grad[0, 0] == 0
    assert (log_variance.grad[valid[0, 0]] != 0).all()


# ----- smoothness prior and bases ----------------------------------------------------------------------------------
def test_smoothness_penalty_equals_loops(generator):
    log_variance = torch.randn(4, 5, generator=generator, dtype=torch.float64)
    valid = torch.rand(4, 5, generator=generator) > 0.3
    expected = 0.0
    for row in range(4):
        for col in range(5):
            for other_row, other_col in ((row + 1, col), (row, col + 1)):
                if other_row < 4 and other_col < 5 and valid[row, col] and valid[other_row, other_col]:
                    expected += 0.5 * float(log_variance[row, col] - log_variance[other_row, other_col]) ** 2
    assert smoothness_penalty(log_variance, valid).item() == pytest.approx(expected, rel=1e-12)
    assert smoothness_penalty(torch.full((3, 3), 2.0)).item() == 0


def test_radial_basis_equals_numpy_legendre_of_the_distance():
    basis = radial_basis((4, 6), 4, center=(1.0, 2.0))
    distances = np.array([[math.hypot(row - 1.0, col - 2.0) for col in range(6)] for row in range(4)])
    argument = 2 * distances / distances.max() - 1
    for order in range(5):
        expected = np.polynomial.legendre.legval(argument, np.eye(5)[order])
        np.testing.assert_allclose(basis[order].numpy(), expected, rtol=1e-12, atol=1e-12)


def test_perspective_basis_reproduces_the_reference():
    truth = camera_truth((16, 16), 2e-5)
    basis = perspective_basis(truth.variance, truth.valid)
    log_geometric_mean = truth.variance[truth.valid].log().mean()
    rebuilt = (log_geometric_mean * basis[0] + basis[1]).exp()
    torch.testing.assert_close(rebuilt[truth.valid], truth.variance[truth.valid])


# ----- the module ----------------------------------------------------------------------------------------------------
def test_pixel_form_ml_is_the_mean_of_squares(generator):
    """The per-pixel ML variance is 1/n sum r^2; the paper's mask (ddof=1) is n/(n-1) times it."""
    local = torch.randn(12, 1, 3, 4, generator=generator, dtype=torch.float64) * 3
    prior = torch.zeros_like(local)
    valid = torch.rand(12, 1, 3, 4, generator=generator) > 0.2
    model = LearnedVariance((3, 4)).double()
    optimizer = torch.optim.LBFGS(model.parameters(), max_iter=200, tolerance_grad=1e-12, tolerance_change=1e-15)

    def closure():
        optimizer.zero_grad()
        loss = model.nll(local, prior, valid, reduction="sum")
        loss.backward()
        return loss

    optimizer.step(closure)
    maximum_likelihood, defined = empirical_variance(local, prior, valid, ddof=0)
    torch.testing.assert_close(model.variance_map()[defined], maximum_likelihood[defined], rtol=1e-6, atol=0)
    paper, _ = empirical_variance(local, prior, valid)
    count = valid.sum(0)[0]
    torch.testing.assert_close(paper[defined] * (count[defined] - 1) / count[defined], maximum_likelihood[defined])


def test_plugs_into_enmi_loss(generator):
    valid = torch.ones(8, 8, dtype=torch.bool)
    valid[:2] = False
    model = LearnedVariance((8, 8), valid=valid, init_variance=30.0)
    with torch.no_grad():
        model.log_variance.add_(torch.randn(8, 8, generator=generator) * 0.3)
    reference = torch.rand(2, 1, 8, 8, generator=generator) * 255
    captured = reference + torch.randn(2, 1, 8, 8, generator=generator) * 5
    captured[:, :, :2] = torch.nan  # out of range: masked by the model
    loss = ENMILoss(bins=8, variance_model=model, reduction="none")(captured, reference)
    expected = 2 - enmi(captured, reference, model.variance_map().float(), bins=8, valid_mask=valid)
    torch.testing.assert_close(loss, expected)
    loss.sum().backward()
    gradient = model.log_variance.grad
    assert torch.isfinite(gradient).all() and (gradient[:2] == 0).all() and (gradient[2:] != 0).any()


def test_forward_dtype_shape_and_valid_mask(dtype):
    model = LearnedVariance((4, 5), init_variance=3.0)
    variance = model(torch.zeros(2, 1, 4, 5, dtype=dtype))
    assert variance.shape == (1, 1, 4, 5) and variance.dtype == dtype
    torch.testing.assert_close(variance, torch.full_like(variance, 3.0))
    assert model.valid_mask(torch.zeros(2, 1, 4, 5)).shape == (1, 1, 4, 5)


@pytest.fixture(scope="module")
def lidar_pairs():
    truth = lidar_truth((24, 24), 4.0, 16.0)
    return truth, stack(SyntheticPairs(truth, 16, seed=3), 16)


def test_radial_form_with_few_pairs_beats_the_empirical_mask(lidar_pairs):
    truth, (local, prior, valid) = lidar_pairs
    empirical, defined = empirical_variance(local, prior, valid)
    start = float(empirical[defined].mean())
    model = fit(LearnedVariance((24, 24), "radial", degree=4, valid=defined, init_variance=start), local, prior, valid)
    learned_error = relative_rms(model.variance_map(), truth.variance, defined)
    empirical_error = relative_rms(empirical, truth.variance, defined)
    assert learned_error < 0.08 < 0.25 < empirical_error


def test_smoothness_prior_helps_with_few_pairs(lidar_pairs):
    truth, (local, prior, valid) = lidar_pairs
    _, defined = empirical_variance(local, prior, valid)
    errors = []
    for smoothness in (0.0, 5.0):
        model = LearnedVariance((24, 24), valid=defined, init_variance=100.0, smoothness=smoothness)
        errors.append(relative_rms(fit(model, local, prior, valid).variance_map(), truth.variance, defined))
    assert errors[1] < 0.6 * errors[0]


def test_perspective_form_recovers_the_noise_power():
    truth = camera_truth((20, 20), 3e-6)
    local, prior, valid = stack(SyntheticPairs(truth, 8, seed=5), 8)
    shape_only = camera_truth((20, 20), 1.0)  # the analytic shape, noise power unknown
    model = LearnedVariance((20, 20), "perspective", valid=truth.valid, analytic_variance=shape_only.variance)
    fit(model, local, prior, valid, steps=300, lr=0.1)
    assert relative_rms(model.variance_map(), truth.variance, truth.valid) < 0.05
    assert model.coefficients[1].item() == pytest.approx(1.0, abs=0.1)


def test_set_valid_recentres_the_perspective_basis():
    truth = camera_truth((12, 12), 1e-6)
    model = LearnedVariance((12, 12), "perspective", valid=truth.valid, analytic_variance=truth.variance)
    smaller = truth.valid.clone()
    smaller[:6] = False
    model.set_valid(smaller)
    assert model.basis[1][smaller].mean().abs() < 1e-5 and torch.equal(model.valid, smaller)
    with pytest.raises(ValueError, match="within the pixels where analytic_variance is defined"):
        model.set_valid(torch.ones(12, 12, dtype=torch.bool))


# ----- files -------------------------------------------------------------------------------------------------------
def perspective_model():
    truth = camera_truth((6, 6), 1e-6)
    return LearnedVariance(
        (6, 6), "perspective", valid=truth.valid, analytic_variance=truth.variance, init_variance=5.0
    )


@pytest.mark.parametrize(
    "make",
    [
        lambda: LearnedVariance((5, 6), valid=torch.rand(5, 6) > 0.3, init_variance=2.0),
        lambda: LearnedVariance((5, 6), "radial", degree=2, center=(1.0, 4.0), smoothness=3.0),
        perspective_model,
    ],
    ids=["pixel", "radial", "perspective"],
)
def test_save_load_round_trip(make, tmp_path, generator):
    model = make()
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.add_(torch.randn(parameter.shape, generator=generator) * 0.1)
    captured = torch.zeros(1, 1, *model.shape)
    for suffix in ("pt", "npy"):
        loaded = LearnedVariance.load(model.save(tmp_path / f"mask.{suffix}"))
        torch.testing.assert_close(loaded.variance_map(), model.variance_map(), equal_nan=True)
        assert torch.equal(loaded.valid_mask(captured), model.valid_mask(captured))
        assert loaded.form == (model.form if suffix == "pt" else "pixel")
    assert np.load(tmp_path / "mask.npy", allow_pickle=False).dtype == np.float32


@pytest.fixture
def saved(tmp_path):
    path = LearnedVariance((3, 3), valid=torch.eye(3, dtype=torch.bool)).save(tmp_path / "good.pt")
    return torch.load(path, weights_only=True)


def tamper(saved, edit):
    payload = {**saved, "config": dict(saved["config"]), "state": dict(saved["state"])}
    edit(payload)
    return payload


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda p: p.update(format="something.else"), "format"),
        (lambda p: p.pop("version"), "keys"),
        (lambda p: p["config"].update(form="cubic"), "form must be one of"),
        (lambda p: p["config"].update(shape=[4, 4]), "valid must be a bool map of shape"),
        (lambda p: p["state"].update(log_variance=torch.zeros(2, 2)), "log_variance"),
        (lambda p: p["state"].update(log_variance=torch.full((3, 3), torch.nan)), "NaN"),
        (lambda p: p["state"].update(valid=torch.ones(3, 3)), "bool"),
        (lambda p: p["state"].update(extra=torch.zeros(1)), "state keys"),
        (lambda p: p.update(state=[1, 2]), "dict of tensors"),
    ],
)
def test_tampered_pt_is_refused(saved, tmp_path, edit, match):
    path = tmp_path / "tampered.pt"
    torch.save(tamper(saved, edit), path)
    with pytest.raises(ValueError, match=match):
        LearnedVariance.load(path)


def test_pickled_objects_are_never_executed(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"format": "enmi_torch.LearnedVariance", "payload": Payload()}, path)
    with pytest.raises(ValueError, match="refused: it is not a plain tensor file"):
        LearnedVariance.load(path)
    evil_npy = tmp_path / "evil.npy"
    np.save(evil_npy, np.array([Payload()], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=r"evil\.npy' is refused: it holds Python objects"):
        LearnedVariance.load(evil_npy)
    assert EXECUTED == []


@pytest.mark.parametrize(
    ("content", "suffix", "match"),
    [
        (b"not a zip file at all", "pt", "refused"),
        (b"a\n", "pt", r"refused: it is not a plain tensor file .*IndexError"),  # the unpickler's own IndexError
        (b"hello\nworld\n", "pt", r"refused: it is not a plain tensor file .*KeyError"),
        (None, "pt-truncated", "refused"),
        (np.ones((2, 3, 3), dtype=np.float32), "npy", "floating"),
        (np.array([[1.0, -2.0], [3.0, np.nan]]), "npy", "> 0 where valid"),
        (np.array([[1.0, np.inf]]), "npy", "> 0 where valid"),
        (np.ones((2, 2), dtype=np.int64), "npy", "floating"),
    ],
)
def test_malformed_files_are_refused(tmp_path, content, suffix, match):
    if suffix == "pt-truncated":
        path = LearnedVariance((3, 3)).save(tmp_path / "cut.pt")
        path.write_bytes(path.read_bytes()[:200])
    elif isinstance(content, bytes):
        path = tmp_path / "bad.pt"
        path.write_bytes(content)
    else:
        path = tmp_path / "bad.npy"
        np.save(path, content)
    with pytest.raises(ValueError, match=match):
        LearnedVariance.load(path)


def test_load_checks_path(tmp_path):
    with pytest.raises(ValueError, match=r"\.pt or \.npy"):
        LearnedVariance.load(tmp_path / "mask.txt")
    with pytest.raises(FileNotFoundError, match="no variance mask file"):
        LearnedVariance.load(tmp_path / "missing.pt")
    with pytest.raises(ValueError, match=r"\.pt or \.npy"):
        LearnedVariance((2, 2)).save(tmp_path / "mask.pkl")


@pytest.mark.parametrize(
    ("make", "error", "match"),
    [
        (lambda: LearnedVariance((0, 3)), ValueError, "shape must be"),
        (lambda: LearnedVariance((3, 3), "cubic"), ValueError, "form must be one of"),
        (lambda: LearnedVariance((3, 3), init_variance=0.0), ValueError, "init_variance"),
        (lambda: LearnedVariance((3, 3), smoothness=-1.0), ValueError, "smoothness"),
        (lambda: LearnedVariance((3, 3), smoothness=math.inf), ValueError, "smoothness"),
        (lambda: LearnedVariance((3, 3), degree=-1), ValueError, "degree"),
        (lambda: LearnedVariance((3, 3), "radial", center=(1.0, math.nan)), ValueError, "center"),
        (lambda: LearnedVariance((3, 3), valid=torch.ones(3, 3)), ValueError, "valid must be a bool map"),
        (lambda: LearnedVariance((3, 3), valid=torch.zeros(3, 3, dtype=torch.bool)), ValueError, "at least one"),
        (lambda: LearnedVariance((3, 3), "perspective"), ValueError, "needs analytic_variance"),
        (
            lambda: LearnedVariance((3, 3), analytic_variance=torch.ones(3, 3)),
            ValueError,
            "only used by form='perspective'",
        ),
        (
            lambda: LearnedVariance((3, 3), "perspective", analytic_variance=-torch.ones(3, 3)),
            ValueError,
            "finite and > 0",
        ),
        (
            lambda: LearnedVariance((3, 3), "perspective", analytic_variance=torch.ones(2, 3)),
            ValueError,
            "analytic_variance must have",
        ),
        (lambda: LearnedVariance((3, 3))(torch.zeros(1, 1, 4, 4)), ValueError, r"\(H, W\) = \(3, 3\)"),
        (lambda: LearnedVariance((3, 3))(torch.zeros(1, 1, 3, 3, dtype=torch.int64)), TypeError, "captured"),
        (
            lambda: LearnedVariance((3, 3)).nll(torch.zeros(1, 1, 3, 3), torch.zeros(1, 1, 3, 3), torch.ones(3, 3)),
            TypeError,
            "bool",
        ),
        (lambda: gaussian_nll(torch.zeros(2, 3, 3), torch.zeros(3, 3), reduction="max"), ValueError, "reduction"),
        (lambda: smoothness_penalty(torch.zeros(3)), ValueError, r"\(H, W\)"),
    ],
)
def test_invalid_inputs(make, error, match):
    with pytest.raises(error, match=match):
        make()


def test_nll_of_a_zero_residual_at_a_huge_precision_is_finite_with_finite_gradients():
    residual = torch.zeros(1, 1, 2, 2, requires_grad=True)
    log_variance = torch.full((2, 2), -1000.0, requires_grad=True)
    loss = gaussian_nll(residual, log_variance)
    loss.backward()
    assert loss.item() == pytest.approx(0.5 * (-1000.0 + math.log(2 * math.pi)))
    assert torch.isfinite(residual.grad).all() and torch.isfinite(log_variance.grad).all()


def test_mean_nll_over_an_all_false_mask_is_refused_and_its_sum_is_zero():
    residual, none = torch.randn(2, 1, 3, 3), torch.zeros(2, 1, 3, 3, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"valid_mask selects no pixel.*mean NLL over no pixel is undefined"):
        gaussian_nll(residual, torch.zeros(3, 3), none)
    assert gaussian_nll(residual, torch.zeros(3, 3), none, reduction="sum").item() == 0.0


def test_a_shape_over_the_memory_budget_is_refused_before_allocating():
    with pytest.raises(MemoryBudgetError, match=r"shape=\(100000, 100000\) needs about 83.8 GiB"):
        LearnedVariance((100_000, 100_000))


def test_load_sizes_a_stride_zero_tensor_from_its_shape_before_copying_it(tmp_path):
    path = LearnedVariance((4, 4)).save(tmp_path / "mask.pt")
    payload = torch.load(path)
    payload["state"]["valid"] = torch.ones(1, dtype=torch.bool).expand(60_000, 60_000)  # a few bytes on disk
    payload["config"]["shape"] = [60_000, 60_000]
    torch.save(payload, path)
    assert path.stat().st_size < 10_000
    with pytest.raises(MemoryBudgetError, match=r"mask.pt: shape=\(60000, 60000\) needs about 30.2 GiB"):
        LearnedVariance.load(path)
    with memory_budget(1 << 30), pytest.raises(MemoryBudgetError, match=r"mask.pt needs about 3.4 GiB for the tensor"):
        LearnedVariance.load(path)
