import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from enmi_torch.functional import enmi, gaussian_log_prior, nmi
from enmi_torch.geometry.camera import RoadCamera
from enmi_torch.simulation import (
    PAPER_ROW_COUNTS,
    SCORES,
    _TrustedScorer,
    count_errors,
    draw_trials,
    error_rates,
    road_tiles,
)

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def paper_tiles():
    return road_tiles(RoadCamera.paper())


def test_paper_tiles_layout(paper_tiles):
    tiles = paper_tiles
    assert tiles.area.numel() == 66
    assert torch.bincount(tiles.row).tolist() == list(PAPER_ROW_COUNTS)
    for row, count in enumerate(PAPER_ROW_COUNTS):
        in_row = tiles.row == row
        low, high = tiles.lateral_low[in_row], tiles.lateral_high[in_row]
        torch.testing.assert_close(high - low, torch.full((count,), 20.0, dtype=torch.float64))
        torch.testing.assert_close(low[1:], high[:-1])  # adjacent, no gaps
        assert low[0].item() == pytest.approx(-10.0 * count) and high[-1].item() == pytest.approx(10.0 * count)
        assert tiles.distance_near[in_row].unique().tolist() == [40.0 + 20.0 * row]
        assert tiles.distance_far[in_row].unique().tolist() == [60.0 + 20.0 * row]
    # Odd rows have a centre tile [-10, 10].
    centre = (tiles.lateral_low == -10.0) & (tiles.lateral_high == 10.0)
    assert int(centre.sum()) == len(PAPER_ROW_COUNTS)


def test_tile_areas_match_the_closed_form_and_the_paper_range(paper_tiles):
    f, h, theta = 0.0367, 58.3095, math.radians(35.9020)

    def depth(distance: float) -> float:
        return distance * math.cos(theta) + h * math.sin(theta)

    for area, near, far, low, high in zip(
        paper_tiles.area.tolist(),
        paper_tiles.distance_near.tolist(),
        paper_tiles.distance_far.tolist(),
        paper_tiles.lateral_low.tolist(),
        paper_tiles.lateral_high.tolist(),
        strict=True,
    ):
        expected = f**2 * h / math.cos(theta) * (high - low) / 2 * (1 / depth(near) ** 2 - 1 / depth(far) ** 2)
        assert area == pytest.approx(expected, rel=1e-12)
    # NOTES.md: about 7.7e-5 cm^2 (nearest row) to 4.7e-6 cm^2 (farthest row); areas shrink with distance.
    assert paper_tiles.area.max().item() == pytest.approx(7.7e-5, rel=0.01)
    assert paper_tiles.area.min().item() == pytest.approx(4.7e-6, rel=0.01)
    row_areas = [paper_tiles.area[paper_tiles.row == row].unique().item() for row in range(8)]
    assert row_areas == sorted(row_areas, reverse=True)


def test_draw_trials_is_seeded_and_follows_the_amplitude_law():
    first = draw_trials(4000, 66, generator=torch.Generator().manual_seed(3))
    again = draw_trials(4000, 66, generator=torch.Generator().manual_seed(3))
    other = draw_trials(4000, 66, generator=torch.Generator().manual_seed(4))
    torch.testing.assert_close(first.amplitudes, again.amplitudes, rtol=0, atol=0)
    torch.testing.assert_close(first.standard_noise, again.standard_noise, rtol=0, atol=0)
    assert not torch.equal(first.amplitudes, other.amplitudes)
    # 264,000 draws: the sample mean and std are within 0.2 and 0.15 of the law (about 3 standard errors).
    for values in (first.amplitudes, first.candidates):
        assert abs(values.mean().item() - 128.0) < 0.2
        assert abs(values.std().item() - 32.0) < 0.15
    assert abs(first.standard_noise.std().item() - 1.0) < 0.005
    correlation = np.corrcoef(first.amplitudes.flatten().numpy(), first.candidates.flatten().numpy())[0, 1]
    assert abs(correlation) < 0.01


def _numpy_nmi(captured: np.ndarray, reference: np.ndarray) -> float:
    """Studholme NMI of 32 hard bins over [0, 256), clipped, from numpy's histogram2d."""
    edges = np.linspace(0, 256, 33)
    counts, _, _ = np.histogram2d(np.clip(captured, 0, 255.999), np.clip(reference, 0, 255.999), bins=[edges, edges])
    return _numpy_nmi_of_counts(counts)


def _numpy_nmi_of_counts(counts: np.ndarray) -> float:
    probability = counts / counts.sum()

    def entropy(p):
        p = p[p > 0]
        return -(p * np.log(p)).sum()

    return (entropy(probability.sum(1)) + entropy(probability.sum(0))) / entropy(probability)


def _numpy_enmi_mass(captured: np.ndarray, reference: np.ndarray, variance: np.ndarray) -> float:
    """ENMI with mass weights, each tile's Gaussian mass per bin from math.erf, tails in the edge bins."""
    counts = np.zeros((32, 32))
    for value, ref, var in zip(captured, reference, variance, strict=True):
        cdf = [0.0] + [0.5 * (1 + math.erf((8.0 * k - value) / math.sqrt(2 * var))) for k in range(1, 32)] + [1.0]
        counts[:, min(max(int(ref // 8), 0), 31)] += np.diff(cdf)
    return _numpy_nmi_of_counts(counts)


@pytest.mark.parametrize("noise_power", [0.003, 0.05])
def test_count_errors_equals_an_independent_numpy_loop(paper_tiles, noise_power):
    trials = draw_trials(60, 66, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    variance = noise_power / paper_tiles.area
    captured = trials.captured(variance)
    nmi_errors = count_errors(captured, trials.amplitudes, trials.candidates, variance, "nmi")
    enmi_errors = count_errors(captured, trials.amplitudes, trials.candidates, variance, "enmi_mass")
    expected_nmi, expected_enmi = [], []
    for v, a, u in zip(captured.numpy(), trials.amplitudes.numpy(), trials.candidates.numpy(), strict=True):
        expected_nmi.append(_numpy_nmi(v, u) >= _numpy_nmi(v, a))
        var = variance.numpy()
        expected_enmi.append(_numpy_enmi_mass(v, u, var) >= _numpy_enmi_mass(v, a, var))
    assert nmi_errors.tolist() == expected_nmi
    assert enmi_errors.tolist() == expected_enmi
    assert 0 < sum(expected_nmi) < 60  # the comparison is not trivial at these noise powers


@pytest.mark.parametrize("score", SCORES)
def test_count_errors_scores_each_reference_like_a_separate_call(paper_tiles, score, dtype):
    trials = draw_trials(40, 66, generator=torch.Generator().manual_seed(2), dtype=dtype)
    variance = (0.03 / paper_tiles.area).to(dtype)
    captured = trials.captured(variance)
    log_prior = gaussian_log_prior(128, 32, 32, (0, 256), dtype=dtype) if score == "enmi_mass_prior" else None
    wrong = count_errors(captured, trials.amplitudes, trials.candidates, variance, score, log_prior=log_prior)

    def separate(reference):  # the trials as flat samples (T, 1, K)
        if score == "nmi":
            return nmi(captured[:, None], reference[:, None], kernel="hard")
        weights = "density" if score == "enmi_density" else "mass"
        return enmi(
            captured[:, None], reference[:, None], variance.reshape(1, 1, -1), kernel=weights, log_prior=log_prior
        )

    assert wrong.tolist() == (separate(trials.candidates) >= separate(trials.amplitudes)).tolist()


@pytest.mark.parametrize("noise_power", [0.002, 0.03, 0.5])
def test_error_rates_count_what_count_errors_counts(paper_tiles, noise_power, dtype):
    result = error_rates(paper_tiles.area, [noise_power], trials=200, seed=4, dtype=dtype)
    trials = draw_trials(200, 66, generator=torch.Generator().manual_seed(4), dtype=dtype)
    variance = noise_power / paper_tiles.area.to(dtype)
    log_prior = gaussian_log_prior(128, 32, 32, (0, 256), dtype=dtype)
    for score in SCORES:
        errors = 0
        for start in range(0, 200, 128):  # the public path, in other chunks
            part = slice(start, start + 128)
            prior = log_prior if score == "enmi_mass_prior" else None
            wrong = count_errors(
                trials.captured(variance, part),
                trials.amplitudes[part],
                trials.candidates[part],
                variance,
                score,
                log_prior=prior,
            )
            errors += int(wrong.sum())
        assert round(result.rates[score].item() * 200) == errors


@pytest.mark.parametrize("score", SCORES)
def test_trusted_scores_are_the_public_scores_bit_for_bit(paper_tiles, score, dtype):
    trials = draw_trials(200, 66, generator=torch.Generator().manual_seed(6), dtype=dtype)
    log_prior = gaussian_log_prior(128, 32, 32, (0, 256), dtype=dtype)
    scorer = _TrustedScorer(trials, 32, (0.0, 256.0), log_prior)
    references = torch.stack([trials.amplitudes, trials.candidates])
    for noise_power in (0.002, 0.5):
        variance = noise_power / paper_tiles.area.to(dtype)
        part = slice(40, 137)
        captured = trials.captured(variance, part)
        flat, flat_references = captured[:, None], references[:, part, None]  # flat samples (T, 1, K)
        if score == "nmi":
            expected = nmi(flat, flat_references, kernel="hard")
        else:
            weights = "density" if score == "enmi_density" else "mass"
            prior = log_prior if score == "enmi_mass_prior" else None
            expected = enmi(flat, flat_references, variance.reshape(1, 1, -1), kernel=weights, log_prior=prior)
        assert torch.equal(scorer.scores(captured, part, variance, score), expected)


def test_error_rates_do_not_depend_on_chunking_or_workers(paper_tiles):
    options = {"trials": 90, "scores": ["nmi", "enmi_mass", "enmi_mass_prior"], "seed": 5}
    reference = error_rates(paper_tiles.area, [0.004, 0.03, 0.3], chunk_trials=90, **options)
    for chunk_trials, workers in ((7, 1), (32, 3)):
        result = error_rates(
            paper_tiles.area, [0.004, 0.03, 0.3], chunk_trials=chunk_trials, workers=workers, **options
        )
        for score in options["scores"]:
            torch.testing.assert_close(result.rates[score], reference.rates[score], rtol=0, atol=0)
    # A point does not depend on which other points run (common random numbers).
    alone = error_rates(paper_tiles.area, [0.03], **options)
    assert alone.rates["nmi"].item() == reference.rates["nmi"][1].item()
    assert 0 < reference.rates["nmi"][1].item() < 1


def test_error_rates_reports_progress_and_time(paper_tiles):
    seen = []
    result = error_rates(
        paper_tiles.area,
        [0.01, 0.1],
        trials=20,
        scores=["nmi"],
        progress=lambda point, rates, seconds: seen.append((point, rates["nmi"], seconds > 0)),
    )
    assert seen == [(index, result.rates["nmi"][index].item(), True) for index in range(2)]
    assert result.seconds["nmi"] > 0
    expected = (result.rates["nmi"] * (1 - result.rates["nmi"]) / 20).sqrt()
    torch.testing.assert_close(result.standard_error("nmi"), expected)


# The issue's assertions. 3000 trials per point: the expected rates (the paper's and our 10,000-trial run) sit at
# least 5 binomial standard errors inside every bound. ENMI <= NMI is checked up to N0 = 0.2, where ENMI is 0 or at
# least 0.1 below NMI; near N0 = 1 both approach 0.5 and the gap (about 0.02) is within the sampling error.
ISSUE_NOISE_POWERS = [0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2]


@pytest.fixture(scope="module")
def issue_rates(paper_tiles):
    return error_rates(paper_tiles.area, ISSUE_NOISE_POWERS, trials=3000, seed=11, chunk_trials=1000)


def test_low_noise_both_scores_almost_never_err(issue_rates):
    low = ISSUE_NOISE_POWERS.index(0.0005)
    for score in SCORES:
        assert issue_rates.rates[score][low].item() < 0.002


def test_at_n0_0_01_nmi_errs_about_a_quarter_of_the_time_and_enmi_rarely(issue_rates):
    point = ISSUE_NOISE_POWERS.index(0.01)
    assert 0.19 <= issue_rates.rates["nmi"][point].item() <= 0.31
    for score in ("enmi_mass", "enmi_density", "enmi_mass_prior"):
        assert issue_rates.rates[score][point].item() < 0.02


def test_enmi_is_never_worse_than_nmi(issue_rates):
    for score in ("enmi_mass", "enmi_density", "enmi_mass_prior"):
        assert bool((issue_rates.rates[score] <= issue_rates.rates["nmi"]).all()), score
    # The amplitude prior (a MAP posterior) helps further where errors are frequent.
    high = ISSUE_NOISE_POWERS.index(0.1)
    assert issue_rates.rates["enmi_mass_prior"][high] < issue_rates.rates["enmi_mass"][high]


@pytest.mark.parametrize(
    ("call", "error", "message"),
    [
        (lambda tiles: road_tiles("camera"), TypeError, "camera must be"),
        (lambda tiles: road_tiles(RoadCamera.paper(), []), ValueError, "row_counts"),
        (lambda tiles: road_tiles(RoadCamera.paper(), [3, 0]), ValueError, "row_counts"),
        (lambda tiles: road_tiles(RoadCamera.paper(), tile_size=-1.0), ValueError, "tile_size"),
        (lambda tiles: road_tiles(RoadCamera.paper(), nearest_distance=0.0), ValueError, "nearest_distance"),
        (lambda tiles: draw_trials(0, 66, generator=torch.Generator()), ValueError, "trials"),
        (lambda tiles: draw_trials(5, 66, generator=0), TypeError, "generator"),
        (lambda tiles: draw_trials(5, 66, generator=torch.Generator(), amplitude_std=0.0), ValueError, "amplitude_std"),
        (lambda tiles: error_rates(tiles.area[None], [0.1]), ValueError, "areas"),
        (lambda tiles: error_rates(-tiles.area, [0.1]), ValueError, "areas"),
        (lambda tiles: error_rates(tiles.area, [0.1, -1.0]), ValueError, "noise_powers"),
        (lambda tiles: error_rates(tiles.area, []), ValueError, "noise_powers"),
        (lambda tiles: error_rates(tiles.area, [0.1], scores=["ssim"]), ValueError, "score"),
        (lambda tiles: error_rates(tiles.area, [0.1], chunk_trials=0), ValueError, "chunk_trials"),
        (lambda tiles: error_rates(tiles.area, [0.1], workers=0), ValueError, "workers"),
        (lambda tiles: error_rates(tiles.area, [0.1], dtype=torch.int32), TypeError, "dtype"),
        (lambda tiles: error_rates(tiles.area, [0.1], bins=1), ValueError, "bins"),
        (
            lambda tiles: count_errors(*torch.ones(3, 2, 66), torch.ones(66), "enmi_mass_prior"),
            ValueError,
            "log_prior",
        ),
        (
            lambda tiles: count_errors(*torch.ones(3, 2, 66), torch.ones(66), "nmi", log_prior=torch.zeros(32)),
            ValueError,
            "log_prior",
        ),
    ],
)
def test_invalid_inputs_raise_clear_errors(paper_tiles, call, error, message):
    with pytest.raises(error, match=message):
        call(paper_tiles)


def test_committed_paper_points_are_the_papers_plot():
    with (REPO / "configs" / "paper_points.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 141
    noise_powers = [float(row["noise_power"]) for row in rows]
    assert noise_powers == sorted(noise_powers) and noise_powers[0] == 0.0002 and noise_powers[-1] == 2.0
    point = next(row for row in rows if row["noise_power"] == "0.01")
    assert (point["nmi"], point["enmi"]) == ("0.2479", "0.0048")


@pytest.mark.slow
def test_full_figure_against_the_papers_points(paper_tiles):
    """The issue's full-run criteria at the config's settings (10,000 trials, seed 0, every N0 of the plot).

    ENMI must be at or below the paper's ENMI within 2 standard errors at every N0. The paper's NMI points scatter
    about a smooth curve with a standard deviation of about 0.013 (a 100,000-trial run puts 10 of them more than
    0.03 from the converged curve), so NMI is held to 0.03 at 125 of the 141 points and to 0.045 at all.
    """
    with (REPO / "configs" / "paper_points.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    paper = {key: torch.tensor([float(row[key]) for row in rows], dtype=torch.float64) for key in rows[0]}
    result = error_rates(paper_tiles.area, paper["noise_power"], trials=10_000, scores=["nmi", "enmi_mass"])
    deviation = (result.rates["nmi"] - paper["nmi"]).abs()
    assert int((deviation <= 0.03).sum()) >= 125
    assert float(deviation.max()) <= 0.045
    paper_stderr = (paper["enmi"] * (1 - paper["enmi"]) / 10_000).sqrt()
    stderr = (result.standard_error("enmi_mass") ** 2 + paper_stderr**2).sqrt()
    assert bool((result.rates["enmi_mass"] <= paper["enmi"] + 2 * stderr).all())
