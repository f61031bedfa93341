"""The model page (docs/model.md): NMI, ENMI, the mixture score and NCC, each equation against the library.

Every test names the equations it checks (``@guards``); the first tests check that every labelled equation of the
page has a test here or in ``test_model_page_ecr.py`` / ``test_model_page_censored.py``, and that every displayed
equation is labelled. The page's side is a direct float64 evaluation of the formula as written.
"""

from __future__ import annotations

import ast
import importlib
import math
import re

import numpy as np
import pytest
import torch
from _model_page import PAGE, guards, hard_bin, image, page_equations, scene
from scipy import special, stats

from enmi_torch import GroundGrid, RoadCamera
from enmi_torch.binning import hard_bin_index
from enmi_torch.functional import enmi, mixture_information, ncc, nmi
from enmi_torch.geometry.camera import projected_area
from enmi_torch.variance import perspective_cell_areas, perspective_variance

BINS, VALUE_RANGE = 8, (0.0, 256.0)
EDGES = np.linspace(*VALUE_RANGE, BINS + 1)
CENTRES = (EDGES[:-1] + EDGES[1:]) / 2


def _guarded_labels() -> dict[str, list[str]]:
    """``{label: [test names]}`` over the ``@guards(...)`` tags of this folder's test files."""
    found: dict[str, list[str]] = {}
    for path in sorted(PAGE.parents[1].joinpath("tests", "docs").glob("test_model_page*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.FunctionDef):
                continue
            for decorator in node.decorator_list:
                if isinstance(decorator, ast.Call) and getattr(decorator.func, "id", None) == "guards":
                    for argument in decorator.args:
                        found.setdefault(argument.value, []).append(f"{path.name}::{node.name}")
    return found


def test_every_equation_of_the_page_is_labelled_and_guarded_by_a_test():
    equations = page_equations()
    assert len(equations) >= 30, "the page's equations were not found"
    unlabelled = [latex.splitlines()[0] for label, latex in equations if label is None]
    assert not unlabelled, f"equations without a label on docs/model.md: {unlabelled}"
    labels = [label for label, _ in equations]
    assert len(labels) == len(set(labels)), "an equation label is used twice"
    guarded = _guarded_labels()
    missing = sorted(set(labels) - set(guarded))
    assert not missing, f"equations of docs/model.md that no test guards: {missing}"
    stale = sorted(set(guarded) - set(labels))
    assert not stale, f"tests guard labels docs/model.md does not have: {stale}"


def test_the_page_names_each_module_that_links_to_it():
    """Each module docstring's link (``:ref:`model-...```) points at a section the page has."""
    text = PAGE.read_text()
    sections = set(re.findall(r"^\((model-[\w-]+)\)=$", text, flags=re.MULTILINE))
    modules = ["ecr", "shrunk_response", "ecr_model_variance", "ecr_regional_misfit", "censoring", "ecr_censored"]
    modules += ["enmi", "nmi", "ncc", "mixture"]
    for name in modules:
        module = importlib.import_module(f"enmi_torch.scores.{name}")
        opening = "\n".join(module.__doc__.split("\n\n")[:2])
        targets = re.findall(r":ref:`[^`<]*<(model-[\w-]+)>`|:ref:`(model-[\w-]+)`", opening)
        targets = [first or second for first, second in targets]
        assert targets, f"{module.__name__}'s opening does not link to the model page"
        assert set(targets) <= sections, f"{module.__name__} links to {targets}, the page has {sorted(sections)}"


# --- Notation and NMI -------------------------------------------------------------------------------------------


@guards("eq-hard-bin")
def test_hard_bin_is_the_clipped_floor():
    values = np.array([-300.0, -1e-9, 0.0, 31.999, 32.0, 100.0, 255.999, 256.0, 1e6])
    expected = hard_bin(values, BINS, VALUE_RANGE)
    assert expected.tolist() == [0, 0, 0, 0, 1, 3, 7, 7, 7]
    assert hard_bin_index(torch.tensor(values, dtype=torch.float64), BINS, VALUE_RANGE).tolist() == expected.tolist()


def _entropy(probability: np.ndarray) -> float:
    """``-sum p log p`` with ``0 log 0 = 0``, a loop."""
    return -sum(p * math.log(p) for p in probability.ravel() if p > 0)


def _nmi_of(counts: np.ndarray) -> float:
    """eq-nmi: ``(H[A] + H[B]) / H[A, B]`` of a joint histogram (captured on axis 0), 1 when ``H[A, B] = 0``."""
    probability = counts / counts.sum()
    joint = _entropy(probability)
    if joint <= np.finfo(np.float64).eps:
        return 1.0
    return (_entropy(probability.sum(1)) + _entropy(probability.sum(0))) / joint


def _joint(captured_weights: np.ndarray, reference_weights: np.ndarray, pixel_weights=None) -> np.ndarray:
    """``J[i, j] = sum_n rho_n q_n(i) k_n(j)`` by a loop over the pixels."""
    counts = np.zeros((captured_weights.shape[1], reference_weights.shape[1]))
    for n in range(captured_weights.shape[0]):
        weight = 1.0 if pixel_weights is None else pixel_weights[n]
        counts += weight * np.outer(captured_weights[n], reference_weights[n])
    return counts


def _one_hot(bins_of_pixels: np.ndarray, bins: int = BINS) -> np.ndarray:
    return np.eye(bins)[bins_of_pixels]


@guards("eq-nmi", "eq-nmi-hard")
@pytest.mark.parametrize("shape", [(6, 9), (20, 31)], ids=["few-pixels", "histogram"])
def test_hard_nmi_is_the_entropy_ratio_of_the_counts(shape):
    captured, reference, _, valid = scene(shape, invalid=5)
    valid_values = captured[valid], reference[valid]
    counts = _joint(
        _one_hot(hard_bin(valid_values[0], BINS, VALUE_RANGE)), _one_hot(hard_bin(valid_values[1], 8, VALUE_RANGE))
    )
    expected = _nmi_of(counts)
    mask = torch.tensor(valid)[None, None]
    got = nmi(image(np.nan_to_num(captured)), image(reference), bins=BINS, kernel="hard", valid_mask=mask)
    assert got.item() == pytest.approx(expected, rel=1e-12)
    assert 1.0 < expected < 2.0


@guards("eq-nmi")
def test_nmi_of_one_cell_is_one():
    flat = np.full((4, 6), 100.0)
    assert _nmi_of(_joint(_one_hot(hard_bin(flat.ravel(), BINS, VALUE_RANGE)), _one_hot(np.zeros(24, int)))) == 1.0
    assert nmi(image(flat), image(flat), bins=BINS, kernel="hard").item() == 1.0


def _parzen(values: np.ndarray, kernel: str) -> np.ndarray:
    """eq-nmi-parzen: ``k(|t_n - i|)``, ``t_n = clip((v_n - l) / Delta - 1/2, 0, K - 1)``, ``(N, K)``."""
    width = (VALUE_RANGE[1] - VALUE_RANGE[0]) / BINS
    position = np.clip((values - VALUE_RANGE[0]) / width - 0.5, 0, BINS - 1)
    distance = np.abs(position[:, None] - np.arange(BINS)[None, :])
    if kernel == "triangular":
        return np.maximum(0.0, 1 - distance)
    inner = 1 - distance * (0.1 + 1.8 * distance)
    outer = np.maximum(0.0, 1.9 - distance * (3.7 - 1.8 * distance))
    return np.where(distance < 0.5, inner, np.where(distance <= 1, outer, 0.0))


@guards("eq-nmi-parzen", "eq-nmi")
@pytest.mark.parametrize("kernel", ["triangular", "xu"])
@pytest.mark.parametrize("reference_kernel", ["hard", "same"])
def test_parzen_nmi_spreads_each_value_by_its_window(kernel, reference_kernel):
    captured, reference, _, _ = scene((7, 12), seed=4)
    captured[0, :3] = [-40.0, 3.0, 300.0]  # beyond the range and inside the edge half-bins
    weights = _parzen(captured.ravel(), kernel)
    assert np.allclose(weights.sum(1), 1.0)
    if reference_kernel == "hard":
        reference_weights = _one_hot(hard_bin(reference.ravel(), BINS, VALUE_RANGE))
    else:
        reference_weights = _parzen(reference.ravel(), kernel)
    expected = _nmi_of(_joint(weights, reference_weights))
    chosen = "hard" if reference_kernel == "hard" else kernel
    got = nmi(image(captured), image(reference), bins=BINS, kernel=kernel, reference_kernel=chosen)
    assert got.item() == pytest.approx(expected, rel=1e-12)


# --- ENMI -------------------------------------------------------------------------------------------------------


def _camera_depth(camera: RoadCamera, distance: float) -> float:
    return distance * math.cos(camera.tilt) + camera.height * math.sin(camera.tilt)


def _area(camera: RoadCamera, lateral: tuple[float, float], distance: tuple[float, float]) -> float:
    """eq-enmi-area: ``f^2 h sec(theta) (x_u - x_l) / 2 (1 / z_l^2 - 1 / z_u^2)``."""
    near, far = (_camera_depth(camera, d) for d in distance)
    scale = camera.focal_length**2 * camera.height / math.cos(camera.tilt)
    return scale * (lateral[1] - lateral[0]) / 2 * (1 / near**2 - 1 / far**2)


def _shoelace_area(camera: RoadCamera, lateral: tuple[float, float], distance: tuple[float, float]) -> float:
    """The tile's image on the focal plane (x~ = f x / z, y~ = f tan(theta) - f h sec(theta) / z) by the shoelace."""
    corners = [
        (lateral[0], distance[0]),
        (lateral[1], distance[0]),
        (lateral[1], distance[1]),
        (lateral[0], distance[1]),
    ]
    f, theta = camera.focal_length, camera.tilt
    points = []
    for x, d in corners:
        z = _camera_depth(camera, d)
        points.append((f * x / z, f * math.tan(theta) - f * camera.height / (math.cos(theta) * z)))
    return 0.5 * abs(sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1) in zip(points, points[1:] + points[:1], strict=True)))


@guards("eq-enmi-area")
@pytest.mark.parametrize("tile", [((-10.0, 10.0), (40.0, 60.0)), ((15.0, 45.0), (120.0, 180.0))])
def test_focal_plane_area_of_a_road_tile(tile):
    camera = RoadCamera.paper()
    expected = _area(camera, *tile)
    assert expected == pytest.approx(_shoelace_area(camera, *tile), rel=1e-12)
    got = projected_area(camera, tile[0][0], tile[0][1], tile[1][0], tile[1][1])
    assert got.item() == pytest.approx(expected, rel=1e-12)


@guards("eq-enmi-variance")
def test_perspective_variance_is_the_noise_power_over_the_area():
    camera, grid, noise_power = RoadCamera.paper(), GroundGrid((-40.0, 20.0), (60.0, 180.0), 20.0), 0.01
    _, valid = perspective_cell_areas(camera, grid)
    assert bool(valid.all())
    lateral, distance = grid.lateral_edges().tolist(), grid.distance_edges().tolist()
    got = perspective_variance(camera, grid, noise_power)[0, 0]
    assert got.shape == (len(distance) - 1, len(lateral) - 1) == (6, 3)
    for row in range(got.shape[0]):  # row 0 is the farthest: the distance edges run from far to near
        for col in range(got.shape[1]):
            tile = ((lateral[col], lateral[col + 1]), (distance[row + 1], distance[row]))
            assert got[row, col].item() == pytest.approx(noise_power / _area(camera, *tile), rel=1e-12)
    assert got[0, 0] > 5 * got[-1, 0]  # far rows far noisier


def _mass(values: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """eq-enmi-mass: ``Phi((e_i+1 - v) / sigma) - Phi((e_i - v) / sigma)``, outer edges at -inf and +inf."""
    edges = EDGES.copy()
    edges[0], edges[-1] = -np.inf, np.inf
    cdf = stats.norm.cdf((edges[None, :] - values[:, None]) / np.sqrt(variance)[:, None])
    return np.diff(cdf, axis=1)


def _density(values: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """eq-enmi-density: the Gaussian at the bin centres, normalised over the bins."""
    log_weights = -((CENTRES[None, :] - values[:, None]) ** 2) / (2 * variance[:, None])
    return special.softmax(log_weights, axis=1)


def _truncated(values: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """eq-enmi-truncated: the masses inside the range, renormalised."""
    cdf = stats.norm.cdf((EDGES[None, :] - values[:, None]) / np.sqrt(variance)[:, None])
    masses = np.diff(cdf, axis=1)
    return masses / masses.sum(1, keepdims=True)


LIKELIHOOD_WEIGHTS = {"mass": _mass, "density": _density, "truncated": _truncated}


def _enmi_scene():
    captured, reference, variance, valid = scene((6, 11), seed=5, invalid=4)
    variance = variance * 3  # up to 5400: some pixels spread over most bins
    captured[1, :2] = [-25.0, 270.0]  # tails beyond the range
    return captured, reference, variance, valid


@guards("eq-enmi-joint", "eq-enmi-mass", "eq-enmi-density", "eq-enmi-truncated")
@pytest.mark.parametrize("kernel", ["mass", "density", "truncated"])
def test_enmi_is_nmi_of_the_likelihood_weighted_histogram(kernel):
    captured, reference, variance, valid = _enmi_scene()
    weights = LIKELIHOOD_WEIGHTS[kernel](captured[valid], variance[valid])
    assert np.allclose(weights.sum(1), 1.0)
    expected = _nmi_of(_joint(weights, _one_hot(hard_bin(reference[valid], BINS, VALUE_RANGE))))
    mask = torch.tensor(valid)[None, None]
    got = enmi(
        image(np.nan_to_num(captured)), image(reference), image(variance), bins=BINS, kernel=kernel, valid_mask=mask
    )
    assert got.item() == pytest.approx(expected, rel=1e-10)


@guards("eq-enmi-prior", "eq-enmi-joint")
@pytest.mark.parametrize("kernel", ["mass", "density"])
def test_a_prior_makes_the_weights_the_posterior(kernel):
    captured, reference, variance, valid = _enmi_scene()
    log_prior = np.log(np.random.default_rng(0).dirichlet(np.ones(BINS)))
    likelihood = LIKELIHOOD_WEIGHTS[kernel](captured[valid], variance[valid])
    posterior = likelihood * np.exp(log_prior)[None, :]
    posterior /= posterior.sum(1, keepdims=True)
    expected = _nmi_of(_joint(posterior, _one_hot(hard_bin(reference[valid], BINS, VALUE_RANGE))))
    got = enmi(
        image(np.nan_to_num(captured)),
        image(reference),
        image(variance),
        bins=BINS,
        kernel=kernel,
        log_prior=torch.tensor(log_prior),
        valid_mask=torch.tensor(valid)[None, None],
    )
    assert got.item() == pytest.approx(expected, rel=1e-10)


@guards("eq-enmi-reliability", "eq-enmi-joint")
def test_reliability_weights_each_pixel_by_its_share_of_signal():
    captured, reference, variance, valid = _enmi_scene()
    values, noise = captured[valid], variance[valid]
    spread = ((values - values.mean()) ** 2).mean()
    signal = max(spread - noise.mean(), spread / 100)
    reliability = signal / (signal + noise)
    counts = _joint(_mass(values, noise), _one_hot(hard_bin(reference[valid], BINS, VALUE_RANGE)), reliability)
    mask = torch.tensor(valid)[None, None]
    got = enmi(
        image(np.nan_to_num(captured)), image(reference), image(variance), bins=BINS, reliability=True, valid_mask=mask
    )
    assert got.item() == pytest.approx(_nmi_of(counts), rel=1e-10)
    unit = enmi(image(np.nan_to_num(captured)), image(reference), image(variance), bins=BINS, valid_mask=mask)
    assert abs(got.item() - unit.item()) > 1e-3  # unequal variances: the weights matter


# --- The mixture score ------------------------------------------------------------------------------------------


def _mixture(captured, reference, variance, valid, em_steps: int) -> float:
    """eq-mixture-joint, eq-mixture-score and eq-mixture-em by loops over the pixels."""
    likelihood = _truncated(captured[valid], variance[valid])
    reference_bins = hard_bin(reference[valid], BINS, VALUE_RANGE)
    count = likelihood.shape[0]
    joint = np.zeros((BINS, BINS))
    for n in range(count):
        joint[:, reference_bins[n]] += likelihood[n]
    per_bin = joint.sum(0)
    conditional = joint / np.where(per_bin > 0, per_bin, 1.0)[None, :]
    marginal = joint.sum(1) / count
    for _ in range(em_steps):
        new_conditional, new_marginal = np.zeros_like(conditional), np.zeros_like(marginal)
        for n in range(count):
            j = reference_bins[n]
            given = likelihood[n] * conditional[:, j]
            new_conditional[:, j] += given / given.sum()
            alone = likelihood[n] * marginal
            new_marginal += alone / alone.sum()
        conditional = new_conditional / np.where(per_bin > 0, per_bin, 1.0)[None, :]
        marginal = new_marginal / count
    total = 0.0
    for n in range(count):
        total += math.log(likelihood[n] @ conditional[:, reference_bins[n]]) - math.log(likelihood[n] @ marginal)
    return total / count


@guards("eq-mixture-joint", "eq-mixture-score", "eq-mixture-em")
@pytest.mark.parametrize("em_steps", [0, 1, 3])
def test_mixture_score_is_the_log_likelihood_ratio_of_two_mixtures(em_steps):
    captured, reference, variance, valid = _enmi_scene()
    expected = _mixture(captured, reference, variance, valid, em_steps)
    got = mixture_information(
        image(np.nan_to_num(captured)),
        image(reference),
        image(variance),
        bins=BINS,
        em_steps=em_steps,
        valid_mask=torch.tensor(valid)[None, None],
    )
    assert got.item() == pytest.approx(expected, rel=1e-10)
    if em_steps:
        assert abs(got.item() - _mixture(captured, reference, variance, valid, 0)) > 1e-4


# --- NCC --------------------------------------------------------------------------------------------------------


@guards("eq-ncc")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ncc_is_pearson_over_the_valid_pixels(dtype):
    captured, reference, _, valid = scene((7, 13), seed=6, response="increasing", invalid=6)
    values, under = captured[valid], reference[valid]
    centred_values, centred_reference = values - values.mean(), under - under.mean()
    expected = (centred_values * centred_reference).sum() / math.sqrt(
        (centred_values**2).sum() * (centred_reference**2).sum()
    )
    mask = torch.tensor(valid)[None, None]
    got = ncc(image(captured, dtype), image(reference, dtype), valid_mask=mask)
    assert got.item() == pytest.approx(expected, rel=1e-12 if dtype == torch.float64 else 1e-5)
