import json
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from kornia.geometry.transform import rotate
from skimage import data

from enmi_torch import ECR, ENMI, NCC, Mixture
from enmi_torch.cli.localize import _command, main
from enmi_torch.functional import ecr_surface
from enmi_torch.localization import NoCandidateError
from enmi_torch.localization.peak import Localization
from enmi_torch.localization.search import Localizer, localize
from enmi_torch.localization.strategy import SearchStrategy
from enmi_torch.placement.peaks import rescore_peaks
from enmi_torch.scores import as_score, direct_surface
from enmi_torch.variance import ConstantVariance, VarianceModel

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def gravel_map() -> torch.Tensor:
    """A 160 x 160 section of scikit-image's gravel texture with a painted lane marking, (1, 1, 160, 160)."""
    section = data.gravel()[100:260, 150:310].astype(np.float64)
    section[:, 70:76] = 235.0
    return torch.from_numpy(section).reshape(1, 1, 160, 160)


def _cut(prior_map, row, col, size=32, yaw=0.0):
    """The ``size`` x ``size`` local image whose centre pixel lies on map cell (row, col), rotated by ``yaw``."""
    half = size // 2
    if yaw == 0:
        return prior_map[..., row - half : row - half + size, col - half : col - half + size].clone()
    margin = size
    big = prior_map[..., row - margin : row + margin, col - margin : col + margin]
    turned = rotate(big, torch.tensor([yaw], dtype=big.dtype))
    return turned[..., margin - half : margin - half + size, margin - half : margin - half + size].clone()


def _noisy(local, std, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return local + std * torch.randn(local.shape, generator=generator, dtype=local.dtype)


@pytest.mark.parametrize("metric", ["ecr", "enmi", "nmi", "ncc"])
def test_known_shifts_are_found_exactly_at_low_noise(gravel_map, dtype, metric):
    prior_map = gravel_map.to(dtype)
    truths = [(3, -5), (-7, 0), (6, 6)]
    local = torch.cat([_noisy(_cut(prior_map, 80 + dy, 80 + dx), 2.0, seed) for seed, (dx, dy) in enumerate(truths)])
    variance = 4.0 if metric in ("ecr", "enmi") else None
    result = localize(local, prior_map, variance, shifts=8, around=(80, 80), score=metric)
    assert isinstance(result, Localization)
    assert result.surface.shape == (3, 1, 17, 17)
    assert result.pose.dtype == dtype
    for sample, (dx, dy) in enumerate(truths):
        grid_peak = divmod(int(result.surface[sample, 0].flatten().argmax()), 17)
        assert grid_peak == (dy + 8, dx + 8)
        assert result.shift[sample].tolist() == pytest.approx([dx, dy], abs=0.25)
        assert result.pose[sample].tolist() == pytest.approx([80 + dx, 80 + dy, 0.0], abs=0.25)  # absolute
        assert result.pose[sample, 2].item() == 0.0
        assert result.margin[sample] > 0
        assert torch.isfinite(result.covariance[sample]).all()


def test_yaw_is_recovered_on_a_rotated_crop(gravel_map):
    local = _noisy(_cut(gravel_map, 84, 77, size=40, yaw=7.0), 2.0)
    result = localize(local, gravel_map, 4.0, shifts=6, around=(80, 80), yaws=range(-12, 13, 3), score=ECR(bins=32))
    x, y, yaw = result.pose[0].tolist()
    assert (round(x), round(y)) == (77, 84)
    assert result.shift[0].round().tolist() == [-3.0, 4.0]
    assert abs(yaw - 7.0) <= 1.0
    profile = result.surface[0].flatten(1).amax(1)
    assert result.yaws[int(profile.argmax())].item() in (6.0, 9.0)


def test_batched_search_over_several_maps_and_centres_equals_single_searches(gravel_map):
    maps = torch.cat([gravel_map, gravel_map.flip(-1)])
    local = torch.cat([_cut(maps[:1], 70, 90), _cut(maps[1:], 95, 60)])
    around = torch.tensor([[88, 72], [63, 92]])  # (x, y)
    batched = localize(local, maps, 9.0, shifts=5, around=around, yaws=[-2.0, 0.0, 2.0], score=ECR(bins=16))
    for sample in range(2):
        single = localize(
            local[sample : sample + 1],
            maps[sample : sample + 1],
            9.0,
            shifts=5,
            around=tuple(around[sample].tolist()),
            yaws=[-2.0, 0.0, 2.0],
            score=ECR(bins=16),
        )
        torch.testing.assert_close(batched.surface[sample], single.surface[0])
        torch.testing.assert_close(batched.pose[sample], single.pose[0])
    assert batched.shift.round().tolist() == [[2.0, -2.0], [-3.0, 3.0]]
    assert batched.pose[:, :2].round().tolist() == [[90.0, 70.0], [60.0, 95.0]]


def test_surface_at_yaw_zero_equals_the_direct_loop_over_the_window(gravel_map):
    local = _noisy(_cut(gravel_map, 80, 80, size=12), 4.0)
    variance = torch.linspace(4, 40, 144, dtype=torch.float64).reshape(1, 1, 12, 12)
    score = ENMI(bins=16)
    result = localize(local, gravel_map, variance, shifts=3, around=(79, 81), min_overlap=0.1, score=score)
    window = gravel_map[..., 81 - 6 - 3 : 81 - 6 + 12 + 3, 79 - 6 - 3 : 79 - 6 + 12 + 3]
    expected = direct_surface(score, local, window, variance)
    torch.testing.assert_close(result.surface[:, 0], expected.score, rtol=0, atol=1e-9)


def test_min_overlap_excludes_candidates_with_too_little_valid_overlap(gravel_map):
    local = _cut(gravel_map, 80, 80)
    reference_mask = torch.ones(160, 160, dtype=torch.bool)
    reference_mask[:, :70] = False
    result = localize(
        local, gravel_map, 9.0, shifts=8, around=(80, 80), reference_mask=reference_mask, min_overlap=0.75
    )
    # Local columns 64 + dx .. 95 + dx; valid map columns >= 70: overlap fraction (96 + dx - 70) / 32 >= 0.75.
    allowed_dx = [dx for dx in range(-8, 9) if (96 + dx - 70) / 32 >= 0.75]
    finite = torch.isfinite(result.surface[0, 0])
    assert finite.any(0).tolist() == [dx in allowed_dx for dx in range(-8, 9)]
    assert finite.all(0).tolist() == finite.any(0).tolist()
    assert result.pose[0, :2].round().tolist() == [80.0, 80.0]
    with pytest.raises(ValueError, match=r"no candidate passes min_overlap in sample\(s\) \[0\]"):
        localize(
            local, gravel_map, 9.0, shifts=(2, 8), around=(60, 80), reference_mask=reference_mask, min_overlap=0.75
        )


def test_candidates_off_the_map_are_scored_on_their_overlap(gravel_map):
    local = _cut(gravel_map, 20, 20)
    result = localize(local, gravel_map, 4.0, shifts=8, around=(16, 16), min_overlap=0.5)
    assert result.pose[0, :2].round().tolist() == [20.0, 20.0]
    # Shifting up/left by 8 leaves (32 - 4)^2 / 32^2 of the image on the map (centre 16 - 8 = 8: rows 8-16 .. 23).
    assert torch.isfinite(result.surface[0, 0, 0, 0])
    tight = localize(local, gravel_map, 4.0, shifts=8, around=(16, 16), min_overlap=1.0)
    assert not torch.isfinite(tight.surface[0, 0, 0, 0])
    assert torch.isfinite(tight.surface[0, 0, 8:, 8:]).all()


def test_fractional_shift_is_refined_below_one_cell():
    rows, cols = torch.meshgrid(torch.arange(96.0), torch.arange(96.0), indexing="ij")
    smooth = 128 + 60 * torch.sin(rows / 5.0) * torch.cos(cols / 7.0) + 40 * torch.sin((rows + cols) / 11.0)
    smooth = smooth.double().reshape(1, 1, 96, 96)
    shifted = 128 + 60 * torch.sin((rows + 0.3) / 5.0) * torch.cos((cols - 0.4) / 7.0)
    shifted = (shifted + 40 * torch.sin((rows + cols - 0.1) / 11.0)).double().reshape(1, 1, 96, 96)
    local = shifted[..., 32:64, 32:64]
    result = localize(local, smooth, score="ncc", shifts=4, around=(48, 48))
    assert result.shift[0].tolist() == pytest.approx([-0.4, 0.3], abs=0.1)


def test_margin_is_the_gap_to_the_best_candidate_outside_the_exclusion_zone(gravel_map):
    local = _noisy(_cut(gravel_map, 80, 80), 8.0)
    result = localize(local, gravel_map, 64.0, shifts=8, around=(80, 80), yaws=[-3.0, 0.0, 3.0], exclusion_radius=2)
    best_over_yaws = result.surface[0].amax(0)
    row, col = divmod(int(best_over_yaws.argmax()), 17)
    outside = best_over_yaws.clone()
    outside[row - 2 : row + 3, col - 2 : col + 3] = -math.inf
    assert result.margin[0].item() == pytest.approx((best_over_yaws.max() - outside.max()).item())
    whole = localize(local, gravel_map, 64.0, shifts=2, around=(80, 80), exclusion_radius=2)
    assert whole.margin[0].item() == math.inf


def test_brick_is_more_ambiguous_than_gravel():
    brick = torch.from_numpy(data.brick()[100:260, 150:310].astype(np.float64)).reshape(1, 1, 160, 160)
    gravel = torch.from_numpy(data.gravel()[100:260, 150:310].astype(np.float64)).reshape(1, 1, 160, 160)
    margins = []
    for prior_map in (brick, gravel):
        local = _noisy(_cut(prior_map, 80, 80), 20.0)
        margins.append(localize(local, prior_map, 400.0, shifts=16, around=(80, 80), score=ECR(bins=16)).margin[0])
    assert margins[0] < margins[1]


@pytest.mark.parametrize("model_variance", [None, "estimate"])
def test_coarse_to_fine_finds_the_exhaustive_pose(gravel_map, model_variance):
    local = _noisy(_cut(gravel_map, 91, 66, yaw=3.0), 3.0)
    # With a fixed tau^2, a fixed delta^2 too: both estimates are read in each fine window.
    response_variance = 30.0 if model_variance is None else "estimate"
    score = ECR(bins=16, model_variance=model_variance, response_variance=response_variance)
    options = {"shifts": 16, "around": (80, 80), "yaws": [0.0, 3.0, 6.0], "score": score}
    exhaustive = localize(local, gravel_map, 9.0, **options)
    coarse = localize(local, gravel_map, 9.0, search=SearchStrategy(coarse_factor=4), **options)
    assert coarse.pose[0].round().tolist() == exhaustive.pose[0].round().tolist() == [66.0, 91.0, 3.0]
    evaluated = torch.isfinite(coarse.surface)
    assert 0 < evaluated.sum() < evaluated.numel() / 3
    if model_variance is None:
        # With fixed variances the fine surfaces are the exhaustive one where evaluated.
        torch.testing.assert_close(coarse.pose, exhaustive.pose)
        torch.testing.assert_close(coarse.surface[evaluated], exhaustive.surface[evaluated])


def test_variance_model_and_its_valid_mask_are_used(gravel_map):
    class DiscVariance(VarianceModel):
        def forward(self, captured):
            return torch.full_like(captured[:1], 9.0)

        def valid_mask(self, captured):
            rows, cols = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
            return ((rows - 15.5) ** 2 + (cols - 15.5) ** 2 <= 12**2).reshape(1, 1, 32, 32)

    local = _cut(gravel_map, 83, 78)
    disc = DiscVariance()
    modelled = localize(local, gravel_map, disc, shifts=5, around=(80, 80))
    explicit = localize(local, gravel_map, 9.0, shifts=5, around=(80, 80), captured_mask=disc.valid_mask(local))
    torch.testing.assert_close(modelled.surface, explicit.surface)
    constant = localize(local, gravel_map, ConstantVariance(9.0), shifts=5, around=(80, 80))
    assert not torch.equal(constant.surface, modelled.surface)


def test_localizer_module_agrees_with_the_function(gravel_map):
    local = _noisy(_cut(gravel_map, 77, 85), 3.0)
    module = Localizer(ConstantVariance(9.0), shifts=6, yaws=[-1.0, 0.0, 1.0], score=ECR(bins=16))
    function = localize(local, gravel_map, 9.0, shifts=6, yaws=[-1.0, 0.0, 1.0], score=ECR(bins=16))
    by_module = module(local, gravel_map)
    torch.testing.assert_close(by_module.surface, function.surface)
    torch.testing.assert_close(by_module.pose, function.pose)
    assert "yaws" not in module.state_dict()
    with pytest.raises(ValueError, match="variance must be None when Localizer has a variance_model"):
        module(local, gravel_map, 9.0)


def test_command_line_prints_the_pose_and_writes_the_surface(gravel_map, tmp_path, capsys):
    from PIL import Image

    np.save(tmp_path / "map.npy", gravel_map[0, 0].numpy())
    local = _cut(gravel_map, 84, 73, size=40, yaw=-4.0)
    Image.fromarray(local[0, 0].round().clamp(0, 255).numpy().astype(np.uint8)).save(tmp_path / "local.png")
    mask = np.ones((40, 40), dtype=bool)
    mask[:4] = False
    np.save(tmp_path / "mask.npy", mask)
    output = tmp_path / "surface.png"
    arguments = ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "local.png"), "--variance", "4"]
    arguments += ["--local-mask", str(tmp_path / "mask.npy"), "--shifts", "10", "--around", "80", "80"]
    arguments += ["--yaws", "-8:0:2", "--output", str(output)]  # a negative value after a space is a value
    report = _command(arguments)
    printed = json.loads(capsys.readouterr().out.splitlines()[0])
    keys = ["x", "y", "yaw_deg", "dx", "dy", "row", "col", "score", "margin"]
    assert printed == report and list(report) == keys
    assert (round(report["x"]), round(report["y"])) == (73, 84)  # the pose: column, row
    assert (round(report["dx"]), round(report["dy"])) == (-7, 4)  # its shift from --around
    assert (report["row"], report["col"]) == (report["y"], report["x"])
    assert abs(report["yaw_deg"] + 4.0) <= 1.0
    assert output.stat().st_size > 1000


def _one_line_error(capsys, arguments) -> str:
    with pytest.raises(SystemExit) as exit_info:
        main(arguments)
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.count("\n") == 1 and error.startswith("enmi-localize: error: ")
    return error


def test_command_line_mistakes_end_in_one_line(gravel_map, tmp_path, capsys):
    np.save(tmp_path / "map.npy", gravel_map[0, 0].numpy())
    local = _cut(gravel_map, 80, 80)[0, 0].numpy()
    np.save(tmp_path / "local.npy", local)
    files = ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "local.npy")]
    assert "needs step > 0 and stop >= start" in _one_line_error(capsys, [*files, "--variance", "4", "--yaws=0:-3:1"])
    assert "variance must be given for score 'ecr'" in _one_line_error(capsys, files)
    assert "(did you mean --variance?)" in _one_line_error(capsys, [*files, "--varience", "4"])
    missing = ["--map", str(tmp_path / "nothing.npy"), "--local", str(tmp_path / "local.npy")]
    assert "--map: no such file" in _one_line_error(capsys, missing)
    (tmp_path / "text.npy").write_text("1 2 3\n")
    text = ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "text.npy"), "--variance", "4"]
    assert "not a .npy file" in _one_line_error(capsys, text)
    local[3, 3] = np.nan
    np.save(tmp_path / "nan.npy", local)
    nan = ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "nan.npy"), "--variance", "4"]
    assert "leave them out with --local-mask FILE" in _one_line_error(capsys, nan)
    assert "--min-overlap must be a fraction" in _one_line_error(
        capsys, [*files, "--variance", "4", "--min-overlap", "2"]
    )
    with pytest.raises(ValueError, match="--min-overlap must be a fraction"):
        main([*files, "--variance", "4", "--min-overlap", "2", "--debug"])


def test_command_line_help_says_what_it_does_with_defaults_an_example_and_the_output(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert text.startswith("usage: enmi-localize") and "Find the pose" in text.split("options:")[0]
    assert "(default: 32)" in text and "example" in text and "output: one JSON line" in text


def _invalid_localize_cases(gravel_map):
    local = _cut(gravel_map, 80, 80)
    return [
        ({"captured": torch.zeros(1, 1, 170, 20)}, ValueError, "captured must not be larger than reference"),
        ({"captured": local.long()}, TypeError, "captured must be a floating-point tensor"),
        ({"reference": torch.cat([gravel_map] * 2)}, ValueError, r"reference must have shape \(1, 1, Hm, Wm\)"),
        (
            {"variance": torch.ones(1, 1, 31, 32)},
            ValueError,
            r"variance must have the spatial shape of captured \(32, 32\)",
        ),
        ({"variance": -torch.ones(32, 32)}, ValueError, "variance must be finite and > 0"),
        ({"score": "enmi", "variance": None}, ValueError, "variance must be given for score 'enmi'"),
        ({"score": "nmi"}, ValueError, "variance is not used by score 'nmi'; pass variance=None"),
        ({"score": lambda: ECR(reliability=True)}, TypeError, "unexpected keyword argument 'reliability'"),
        ({"score": lambda: ECR(em_steps=2)}, TypeError, "unexpected keyword argument 'em_steps'"),
        ({"score": "ecr", "variance": None}, ValueError, "variance must be given for score 'ecr'"),
        ({"score": lambda: ECR(model_variance=-1.0)}, ValueError, "model_variance must be 'estimate', a number >= 0"),
        ({"score": lambda: ENMI(model_variance=1.0)}, TypeError, "unexpected keyword argument 'model_variance'"),
        ({"score": "mi"}, ValueError, "score must be a Score or one of"),
        ({"captured_mask": torch.zeros(32, 32, dtype=torch.bool)}, ValueError, "captured_mask selects no pixel"),
        ({"captured_mask": torch.ones(32, 32)}, TypeError, "captured_mask must be a bool tensor"),
        (
            {"reference_mask": torch.zeros(160, 160, dtype=torch.bool)},
            ValueError,
            r"reference_mask selects no pixel in sample\(s\) \[0\]",
        ),
        (
            {"reference_mask": torch.ones(16, 16, dtype=torch.bool)},
            ValueError,
            r"reference_mask must have the spatial shape of reference \(160, 160\)",
        ),
        ({"shifts": -1}, ValueError, "shifts must be an int >= 0"),
        ({"shifts": (2, 2.5)}, ValueError, "shifts must be an int >= 0"),
        ({"yaws": []}, ValueError, "yaws must be a non-empty sequence"),
        ({"yaws": [0.0, math.nan]}, ValueError, "yaws must be a non-empty sequence"),
        ({"around": (80.0, math.nan)}, ValueError, r"around must be finite map cells \(x, y\)"),
        ({"around": (80, 80, 0.0)}, ValueError, r"around must be \(x, y\) numbers .*a pose's yaw is not taken"),
        ({"around": torch.zeros(1, 3)}, ValueError, r"around must be \(x, y\) or a real tensor .*float32 \(1, 3\)"),
        ({"around": "80, 80"}, ValueError, r"around must be \(x, y\) numbers or a \(B, 2\) tensor, got '80, 80'"),
        ({"min_overlap": 0.0}, ValueError, r"min_overlap must be a fraction in \(0, 1\]"),
        ({"exclusion_radius": -2}, ValueError, "exclusion_radius must be an int >= 0"),
        ({"search": lambda: SearchStrategy(coarse_factor=0)}, ValueError, "coarse_factor must be an int >= 1"),
        (
            {"search": SearchStrategy(coarse_factor=64)},
            ValueError,
            "coarse_factor must not exceed the captured image size",
        ),
        ({"score": lambda: ECR(bins=1)}, ValueError, "bins must be an int >= 2"),
        ({"score": lambda: ENMI(kernel="gauss")}, ValueError, "kernel must be one of"),
        ({"resample": "bicubic"}, ValueError, "resample must be one of"),
        ({"search": "greedy"}, ValueError, "search must be one of"),
        ({"search": "two_stage", "score": "enmi"}, ValueError, "search='two_stage' needs a score with the 'two_stage'"),
        (
            {"search": "two_stage", "score": lambda: ECR(response="linear")},
            ValueError,
            r"search='two_stage' needs .*score=ECR\(.*response='linear'.* \(ECR with response='shrunk' or 'binned'\)",
        ),
        (
            {"search": lambda: SearchStrategy("two_stage", coarse_factor=2)},
            ValueError,
            "search='two_stage' needs coarse_factor=1",
        ),
        (
            {"search": SearchStrategy("two_stage", cheap_bins=64)},
            ValueError,
            r"cheap_bins must be at most bins \(32\)",
        ),
        ({"search": lambda: SearchStrategy("two_stage", cheap_bins=1)}, ValueError, "cheap_bins must be an int >= 2"),
        ({"cheap_bins": 8}, TypeError, r"localize\(\) takes cheap_bins in search=SearchStrategy\(\.\.\.\)"),
    ], local


@pytest.mark.parametrize("index", range(39))
def test_invalid_inputs_raise_clear_errors(gravel_map, index):
    cases, local = _invalid_localize_cases(gravel_map)
    change, error, message = cases[index]
    arguments = {"captured": local, "reference": gravel_map, "variance": 9.0, "shifts": 4}
    arguments.update(change)
    with pytest.raises(error, match=message):
        for name in ("score", "search"):  # a score or strategy whose options are wrong fails as it is built
            if callable(arguments.get(name)):
                arguments[name] = arguments[name]()
        localize(**arguments)


def test_ecr_search_with_unequal_radii_and_a_noisy_far_half_equals_the_direct_loop(gravel_map):
    # A camera-like variance: the top rows are 100 times noisier than the bottom rows.
    local = _cut(gravel_map, 83, 78, size=24)[..., :, :20]
    variance = torch.logspace(2, 0, 24, dtype=torch.float64).reshape(24, 1).expand(24, 20) * 4
    local = (
        local
        + torch.randn(local.shape, generator=torch.Generator().manual_seed(5), dtype=local.dtype) * variance.sqrt()
    )
    result = localize(local, gravel_map, variance, shifts=(3, 5), around=(80, 80), score="ecr", min_overlap=0.1)
    assert result.surface.shape == (1, 1, 7, 11)
    assert result.pose[0, :2].round().tolist() == [76.0, 83.0]
    window = gravel_map[..., 80 - 12 - 3 : 80 - 12 + 24 + 3, 80 - 10 - 5 : 80 - 10 + 20 + 5]
    expected = direct_surface("ecr", local, window, variance)
    torch.testing.assert_close(result.surface[:, 0], expected.score, rtol=0, atol=1e-9)


def test_mixture_search_rescores_its_best_shifts_exactly_and_finds_the_pose(gravel_map):
    local = _noisy(_cut(gravel_map, 83, 78, size=20)[..., :, :18], 6.0)
    variance = torch.linspace(4, 400, 20 * 18, dtype=torch.float64).reshape(20, 18)
    result = localize(local, gravel_map, variance, shifts=(3, 4), around=(80, 80), score=Mixture(bins=16))
    assert result.surface.shape == (1, 1, 7, 9)
    assert result.pose[0, :2].round().tolist() == [77.0, 83.0]
    window = gravel_map[..., 80 - 10 - 3 : 80 - 10 + 20 + 3, 80 - 9 - 4 : 80 - 9 + 18 + 4]
    expected = direct_surface(Mixture(bins=16), local, window, variance).score
    rescored = torch.isfinite(result.surface[:, 0])
    assert 9 <= int(rescored.sum()) < 63
    torch.testing.assert_close(result.surface[:, 0][rescored], expected[rescored], rtol=0, atol=1e-9)
    assert int(expected.flatten().argmax()) == int(result.surface[:, 0].flatten().argmax())


@pytest.mark.parametrize("yaws", [[0.0], [-2.0, 2.0]])
def test_a_log_prior_per_sample_applies_to_that_sample_at_every_yaw(gravel_map, yaws):
    from enmi_torch.functional import gaussian_log_prior

    local = torch.cat([_noisy(_cut(gravel_map, 78, 83), 6.0, 1), _noisy(_cut(gravel_map, 84, 77), 6.0, 2)])
    priors = torch.stack(
        [gaussian_log_prior(90.0, 20.0, 16, (0.0, 256.0)), gaussian_log_prior(160.0, 50.0, 16, (0.0, 256.0))]
    )
    options = {"shifts": 4, "around": (80, 80), "yaws": yaws}
    batched = localize(local, gravel_map, 36.0, score=ENMI(bins=16, log_prior=priors.double()), **options)
    for sample in range(2):
        score = ENMI(bins=16, log_prior=priors[sample].double())
        single = localize(local[sample : sample + 1], gravel_map, 36.0, score=score, **options)
        torch.testing.assert_close(batched.surface[sample], single.surface[0])
    other = localize(local[:1], gravel_map, 36.0, score=ENMI(bins=16, log_prior=priors[1].double()), **options)
    assert not torch.allclose(batched.surface[0], other.surface[0])
    module = Localizer(shifts=4, yaws=yaws, score=ENMI(bins=16, log_prior=priors[0].double()))
    torch.testing.assert_close(module(local[:1], gravel_map, 36.0, around=(80, 80)).surface, batched.surface[:1])


def test_ecr_linear_response_in_the_search_equals_the_direct_loop(gravel_map):
    local = _noisy(_cut(gravel_map, 82, 79, size=16), 5.0) * 0.8 + 12
    linear = ECR(response="linear")
    result = localize(local, gravel_map, 25.0, shifts=(2, 3), around=(80, 80), score=linear, min_overlap=0.1)
    window = gravel_map[..., 80 - 8 - 2 : 80 - 8 + 16 + 2, 80 - 8 - 3 : 80 - 8 + 16 + 3]
    expected = direct_surface(linear, local, window, 25.0)
    torch.testing.assert_close(result.surface[:, 0], expected.score, rtol=0, atol=1e-9)
    assert result.pose[0, :2].round().tolist() == [79.0, 82.0]
    with pytest.raises(TypeError, match="response"):
        localize(local, gravel_map, 25.0, score=ENMI(response="linear"))


def test_local_to_map_transform_points_each_local_pixel_at_the_map_it_shows(gravel_map):
    # A rotated cut on a non-square local image: a swapped axis or a mirrored yaw puts pixels on other map cells.
    local = _cut(gravel_map, 86, 75, size=40, yaw=8.0)[..., 4:36, :]  # (1, 1, 32, 40)
    options = {"shifts": (8, 9), "around": (80, 80), "yaws": range(-12, 13, 2), "score": ECR(bins=32)}
    result = localize(local, gravel_map, 4.0, **options)
    assert result.dx.shape == result.yaw.shape == (1,)
    assert abs(result.yaw.item() - 8.0) <= 1.0
    rows, cols = torch.meshgrid(torch.arange(8.0, 24.0), torch.arange(8.0, 32.0), indexing="ij")  # interior
    points = torch.stack([cols.flatten(), rows.flatten(), torch.ones(rows.numel())]).double()

    def mismatch(transform):
        mapped = (transform[0] @ points)[:2]
        size = gravel_map.shape[-1]
        grid = (mapped.T / (size - 1) * 2 - 1).reshape(1, -1, 1, 2)
        sampled = torch.nn.functional.grid_sample(gravel_map, grid, align_corners=True)[0, 0, :, 0]
        return (sampled - local[0, 0, 8:24, 8:32].flatten()).abs().mean().item()

    right = mismatch(result.local_to_map((32, 40)))
    assert right < 3.0  # grey levels: the sampled map reproduces the local image (the texture varies by ~40)
    mirrored = Localization(result.pose * torch.tensor([1.0, 1.0, -1.0], dtype=result.pose.dtype), *result[1:])
    swapped = Localization(result.pose[:, [1, 0, 2]], *result[1:])
    assert right < 0.5 * mismatch(mirrored.local_to_map((32, 40)))
    assert right < 0.5 * mismatch(swapped.local_to_map((32, 40)))
    assert right < 0.5 * mismatch(result.local_to_map((40, 32)))
    with pytest.warns(DeprecationWarning, match=r"local_to_map\(center, local_shape\) is deprecated"):
        former = result.local_to_map((80, 80), (32, 40))  # the former call: center (row, col) + the shift
    torch.testing.assert_close(former, result.local_to_map((32, 40)))


def test_yaw_parabola_and_yaw_ranges_are_exact():
    from enmi_torch.cli.localize import _parse_yaws
    from enmi_torch.localization.peak import _parabola_offset

    # A parabola with its vertex 0.3 steps right of the middle sample.
    values = torch.tensor([-((x - 0.3) ** 2) for x in (-1.0, 0.0, 1.0)], dtype=torch.float64)
    assert _parabola_offset(values).item() == pytest.approx(0.3)
    assert _parabola_offset(values * 7 + 4).item() == pytest.approx(0.3)
    assert _parse_yaws("-6:6:2") == [-6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0]
    assert _parse_yaws("0:1:0.25") == [0.0, 0.25, 0.5, 0.75, 1.0]


def _two_stage_case(gravel_map, seed):
    """Two rotated, noisy crops (unequal sizes, a camera-like variance) with masks, two centres, five yaws."""
    generator = torch.Generator().manual_seed(seed)
    truths = torch.randint(-3, 4, (2, 2), generator=generator).tolist()
    yaws = [-4.0, -2.0, 0.0, 2.0, 4.0]
    picks = torch.randint(0, len(yaws), (2,), generator=generator).tolist()
    crops = [
        _cut(gravel_map, 80 + dy, 76 + dx, size=24, yaw=yaws[pick])
        for (dx, dy), pick in zip(truths, picks, strict=True)
    ]
    local = torch.cat(crops)[..., :, :20]
    variance = torch.logspace(1, 0, 24, dtype=torch.float64).reshape(24, 1).expand(24, 20) * 9
    local = local + torch.randn(local.shape, generator=generator, dtype=local.dtype) * variance.sqrt()
    captured_mask = torch.ones(24, 20, dtype=torch.bool)
    captured_mask[:3, :4] = False
    reference_mask = torch.ones(160, 160, dtype=torch.bool)
    reference_mask[65:68, 60:95] = False  # crosses the top rows of the images near the truth: min_overlap bites
    options = {
        "shifts": (4, 5),
        "around": torch.tensor([[76, 80], [76, 80]]),
        "yaws": yaws,
        "score": ECR(bins=16),
        "captured_mask": captured_mask,
        "reference_mask": reference_mask,
        "min_overlap": 0.97,
    }
    return local, variance, options


@pytest.mark.parametrize("seed", range(3))
def test_two_stage_search_equals_the_exhaustive_search_where_it_rescored_and_finds_its_argmax(gravel_map, seed):
    local, variance, options = _two_stage_case(gravel_map, seed)
    # A fixed tau^2 and delta^2: min_overlap=0.97 leaves out placements where the exhaustive surface may read estimated
    # ones (tests/scores/test_ecr_model_variance.py checks the estimates at the default min_overlap).
    options["score"] = options["score"].replace(model_variance=None, response_variance=40.0)
    exhaustive = localize(local, gravel_map, variance, **options)
    two_stage = localize(local, gravel_map, variance, search=SearchStrategy("two_stage", cheap_bins=4), **options)
    rescored = torch.isfinite(two_stage.surface)
    assert two_stage.surface.shape == exhaustive.surface.shape == (2, 5, 9, 11)
    for sample in range(2):
        assert 27 <= int(rescored[sample].sum()) < rescored[sample].numel() // 2
    torch.testing.assert_close(two_stage.surface[rescored], exhaustive.surface[rescored], rtol=0, atol=1e-9)
    assert torch.equal(two_stage.surface.flatten(1).argmax(1), exhaustive.surface.flatten(1).argmax(1))
    torch.testing.assert_close(two_stage.pose, exhaustive.pose, rtol=0, atol=1e-9)
    torch.testing.assert_close(two_stage.covariance, exhaustive.covariance, rtol=0, atol=1e-9)
    # The best candidate's 3 x 3 shifts at its yaw and both neighbouring yaws were rescored (the sub-cell fits):
    # finite, or excluded by min_overlap in the exhaustive search too.
    known = rescored | torch.isinf(exhaustive.surface)
    assert bool((~known).any())
    for sample in range(2):
        yaw, rest = divmod(int(two_stage.surface[sample].flatten().argmax()), 9 * 11)
        row, col = divmod(rest, 11)
        around = known[sample, max(yaw - 1, 0) : yaw + 2, max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2]
        assert bool(around.all())


def test_localizer_module_runs_the_two_stage_search_like_the_function(gravel_map):
    local, variance, options = _two_stage_case(gravel_map, 1)
    around = options.pop("around")
    masks = {name: options.pop(name) for name in ("captured_mask", "reference_mask")}
    options.update(search=SearchStrategy("two_stage", cheap_bins=8))
    result = Localizer(**options)(local, gravel_map, variance, around=around, **masks)
    expected = localize(local, gravel_map, variance, around=around, **options, **masks)
    assert torch.equal(result.surface, expected.surface)
    assert bool(torch.isinf(result.surface).any())


def test_two_stage_search_in_float32_finds_the_exhaustive_pose(gravel_map):
    local, variance, options = _two_stage_case(gravel_map, 3)
    local, variance = local.float(), variance.float()
    exhaustive = localize(local, gravel_map.float(), variance, **options)
    two_stage = localize(local, gravel_map.float(), variance, search="two_stage", **options)
    assert two_stage.surface.dtype == torch.float32
    rescored = torch.isfinite(two_stage.surface)
    torch.testing.assert_close(two_stage.surface[rescored], exhaustive.surface[rescored], rtol=1e-5, atol=1e-5)
    assert torch.equal(two_stage.surface.flatten(1).argmax(1), exhaustive.surface.flatten(1).argmax(1))


def test_rescoring_over_yaws_doubles_its_peaks_and_completes_the_best_neighbourhood():
    # Cheap surface: peaks on a grid, ranked the farther from the target the better; exact score: the nearer the
    # better, so the exact best always sits by the lowest-ranked peak and the number of peaks doubles up to the limit;
    # the target lies on the rim of the last peak's neighbourhood.
    target = (3, 10, 2)  # one yaw and one cell beyond the peak (2, 9, 1)
    cheap = torch.full((4, 12, 12), -1.0, dtype=torch.float64)
    peaks = [(yaw, row, col) for yaw in (0, 2) for row in (1, 5, 9) for col in (1, 6)]
    peaks.sort(key=lambda peak: -sum(abs(a - b) for a, b in zip(peak, target, strict=True)))
    for rank, peak in enumerate(peaks):
        cheap[peak] = 100.0 - rank

    def exact(placements):
        distance = (placements - torch.tensor(target)).abs().sum(-1).to(torch.float64)
        return 50.0 - distance

    score = rescore_peaks(cheap, exact, 2, 64, complete_best=True)
    assert int(score.argmax()) == 3 * 144 + 10 * 12 + 2
    assert all(bool(torch.isfinite(score[peak])) for peak in peaks)  # 2 -> 4 -> 8 -> 12 peaks
    assert bool(torch.isfinite(score[2:4, 9:12, 1:4]).all())  # the best's own neighbourhood, completed
    without = rescore_peaks(cheap, exact, 2, 64)
    assert not bool(torch.isfinite(without[2:4, 9:12, 1:4]).all())
    assert int(without.argmax()) == int(score.argmax())


@pytest.mark.parametrize("reference_masked", [False, True])
def test_cheap_stage_equals_the_ecr_surface_in_float64(gravel_map, reference_masked):
    # Occupied bins read from the weight sums agree with the exact counts once round-off is far below a pixel weight.
    local, variance, options = _two_stage_case(gravel_map, 4)
    window = gravel_map[..., 60:100, 50:90]
    reference_mask = options["reference_mask"][60:100, 50:90] if reference_masked else None
    masks = {"captured_mask": options["captured_mask"], "reference_mask": reference_mask}
    cheap = ECR(bins=6, value_range=(40.0, 200.0)).rough_surface(local, window, variance, **masks)
    expected = ecr_surface(local, window, variance, bins=6, value_range=(40.0, 200.0), response="binned", **masks)
    torch.testing.assert_close(cheap.score, expected.score, rtol=0, atol=1e-9)
    torch.testing.assert_close(cheap.overlap, expected.overlap, rtol=0, atol=0)


def test_two_stage_search_keeps_candidates_with_exactly_the_required_overlap(gravel_map):
    local = _cut(gravel_map, 82, 77)
    # With min_overlap 1 every candidate inside the map needs all its pixels: the overlap equals the requirement.
    options = {"shifts": (4, 6), "around": (80, 80), "min_overlap": 1.0}
    exhaustive = localize(local, gravel_map, 25.0, **options)
    two_stage = localize(local, gravel_map, 25.0, search="two_stage", **options)
    torch.testing.assert_close(two_stage.pose, exhaustive.pose)
    assert two_stage.pose.round().tolist() == [[77.0, 82.0, 0.0]]


@pytest.mark.parametrize("name", ["ecr", "enmi", "nmi", "ncc", "mixture"])
def test_a_score_by_name_or_by_object_gives_identical_poses(gravel_map, name):
    local = _noisy(_cut(gravel_map, 82, 77, size=20), 3.0)
    variance = None if name in ("nmi", "ncc") else 9.0
    options = {"shifts": (3, 4), "around": (80, 80), "yaws": [-2.0, 0.0, 2.0]}
    by_name = localize(local, gravel_map, variance, score=name, **options)
    by_object = localize(local, gravel_map, variance, score=as_score(name), **options)
    assert torch.equal(by_name.surface, by_object.surface) and torch.equal(by_name.pose, by_object.pose)
    around = options.pop("around")
    module = Localizer(score=name, **options)(local, gravel_map, variance, around=around)
    assert torch.equal(module.surface, by_object.surface)
    assert Localizer(score=name).score == as_score(name)


def test_command_line_builds_the_score_from_its_flags_and_keeps_the_old_one(gravel_map, tmp_path, capsys):
    np.save(tmp_path / "map.npy", gravel_map[0, 0].numpy())
    local = _noisy(_cut(gravel_map, 83, 78, size=24), 3.0)
    np.save(tmp_path / "local.npy", local[0, 0].numpy())
    files = ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "local.npy"), "--shifts", "4"]
    files += ["--around", "80", "80", "--dtype", "float64"]

    def expected(score, variance=4.0):
        result = localize(local, gravel_map, variance, score=score, shifts=4, around=(80, 80))
        return round(float(result.score[0]), 4), [round(value, 2) for value in result.pose[0, :2].tolist()]

    def printed(arguments):
        report = _command([*files, *arguments])
        capsys.readouterr()
        return report["score"], [report["x"], report["y"]]

    density = ["--bins", "16", "--score-option", "kernel=density", "--score-option", "log_prior=None"]
    assert printed(["--variance", "4", "--score", "enmi", *density]) == expected(ENMI(bins=16, kernel="density"))
    assert printed(["--variance", "4", "--metric", "enmi", *density]) == expected(ENMI(bins=16, kernel="density"))
    tau = ["--score-option", "model_variance=2.5", "--value-range", "0", "200"]
    assert printed(["--variance", "4", *tau]) == expected(ECR(model_variance=2.5, value_range=(0.0, 200.0)))
    assert printed(["--score", "ncc", "--bins", "1"]) == expected(NCC(), None)  # NCC has no bins to check
    unknown = _one_line_error(capsys, [*files, "--variance", "4", "--score-option", "em_steps=2"])
    assert "--score-option takes KEY=VALUE with KEY one of ECR's options ['bins', 'value_range', 'model_variance'" in (
        unknown
    )
    assert "got 'em_steps=2'" in unknown
    assert "response must be one of" in _one_line_error(
        capsys, [*files, "--variance", "4", "--score-option", "response=cubic"]
    )
    assert "--value-range must be finite with low < high" in _one_line_error(
        capsys, [*files, "--variance", "4", "--value-range", "5", "1"]
    )
    assert "--score-option takes KEY=VALUE" in _one_line_error(capsys, [*files, "--score-option", "kernel"])


def test_command_line_hints_work_as_written(gravel_map, tmp_path, capsys):
    """The [0, 1] hint's --value-range parses and fixes the run; a PNG reads without torch's read-only warning."""
    from PIL import Image

    unit = gravel_map[0, 0].numpy() / 255.0
    np.save(tmp_path / "map.npy", unit)
    np.save(tmp_path / "local.npy", unit[64:96, 64:96])
    files = ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "local.npy"), "--variance", "0.001"]
    for score in ("ecr", "enmi"):  # ECR bins the map, ENMI the captured image: both refuse one bin, name the flag
        error = _one_line_error(capsys, [*files, "--score", score, "--shifts", "4", "--around", "80", "80"])
        hint = re.search(r"\(e\.g\. (--value-range [^ ]+ [^ ]+) for", error)
        assert hint is not None, error
        report = _command([*files, "--score", score, "--shifts", "4", "--around", "80", "80", *hint.group(1).split()])
        assert (round(report["dx"]), round(report["dy"])) == (0, 0)
        capsys.readouterr()
    Image.fromarray(gravel_map[0, 0].numpy().astype(np.uint8)).save(tmp_path / "map.png")
    Image.fromarray(gravel_map[0, 0, 64:96, 64:96].numpy().astype(np.uint8)).save(tmp_path / "local.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # torch warns on a read-only array: none here
        _command(["--map", str(tmp_path / "map.png"), "--local", str(tmp_path / "local.png"), "--variance", "4"])


def test_a_nan_is_refused_naming_the_mask_argument_of_the_function(gravel_map):
    local = _cut(gravel_map, 80, 80).clone()
    local[..., 3, 3] = float("nan")
    with pytest.raises(ValueError, match=r"captured must be finite where captured_mask is True.*with captured_mask"):
        localize(local, gravel_map, 9.0, shifts=4, around=(80, 80))
    reference = gravel_map.clone()
    reference[..., 80, 80] = float("nan")
    with pytest.raises(ValueError, match="reference must be finite where reference_mask is True"):
        localize(_cut(gravel_map, 80, 80), reference, 9.0, shifts=4, around=(80, 80))


@pytest.mark.parametrize("shape", [(1, 1), (8, 8)])
def test_a_captured_image_of_one_value_is_refused_not_placed_at_the_windows_corner(gravel_map, shape):
    # Every placement scores alike: the "peak" was the window's first cell (dx -4, dy -4, score 0).
    flat = torch.full((1, 1, *shape), 120.0, dtype=torch.float64)
    if shape == (1, 1):
        flat = gravel_map[..., 80:81, 80:81].clone()
    for score, variance in (("ecr", 4.0), ("nmi", None), ("ncc", None)):
        with pytest.raises(NoCandidateError, match=r"captured sample\(s\) \[0\] hold one value at all their"):
            localize(flat, gravel_map, variance, shifts=4, score=score)
    masked = _cut(gravel_map, 80, 80, size=8).clone()
    mask = torch.zeros(1, 1, 8, 8, dtype=torch.bool)
    mask[..., 2, 3] = True  # one valid pixel is one value too
    with pytest.raises(NoCandidateError, match=r"hold one value at all their 1 valid pixel\(s\)"):
        localize(masked, gravel_map, 4.0, shifts=4, captured_mask=mask)


def test_command_line_refuses_a_one_pixel_image_and_an_output_folder_before_searching(gravel_map, tmp_path, capsys):
    np.save(tmp_path / "map.npy", gravel_map[0, 0].numpy())
    np.save(tmp_path / "pixel.npy", gravel_map[0, 0, 80:81, 80:81].numpy())
    np.save(tmp_path / "local.npy", _cut(gravel_map, 80, 80)[0, 0].numpy())
    pixel = ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "pixel.npy"), "--variance", "4"]
    assert "--local sample(s) [0] hold one value" in _one_line_error(capsys, [*pixel, "--shifts", "4"])
    files = ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "local.npy"), "--variance", "4"]
    folder = tmp_path / "surfaces"
    folder.mkdir()
    error = _one_line_error(capsys, [*files, "--output", str(folder)])
    assert f"--output must name a PNG file to write, got the existing folder '{folder}'" in error
    assert list(tmp_path.glob("surfaces*")) == [folder] and not list(folder.iterdir())  # no surfaces.png beside it
    assert "lies in a folder that does not exist" in _one_line_error(capsys, [*files, "--output", str(folder / "a/b")])
    _command([*files, "--shifts", "4", "--output", str(tmp_path / "surface")])  # no suffix: written as named
    assert (tmp_path / "surface").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert capsys.readouterr().err.strip() == f"wrote {tmp_path / 'surface'}"


def _scene():
    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(1, 1, 48, 48, generator=generator) * 256
    return reference[..., 14:30, 19:35].clone(), reference


def test_an_off_map_window_is_told_it_lies_off_the_map():
    captured, reference = _scene()
    with pytest.raises(NoCandidateError, match=r"the search window lies off the map in sample\(s\) \[0\]"):
        localize(captured, reference, 64.0, score=ECR(bins=16), shifts=3, around=(500, 500))


def test_huge_yaws_are_refused_by_name_and_turns_are_taken_modulo_360():
    captured, reference = _scene()
    with pytest.raises(ValueError, match=r"yaws must be angles within \+-1e\+06 degrees .* got 1e\+300"):
        localize(captured, reference, 64.0, score=ECR(bins=16), shifts=3, yaws=[1e300])
    turned = localize(captured, reference, 64.0, score=ECR(bins=16), shifts=3, yaws=[-720.0, 5.0 - 720.0])
    assert turned.pose[0, :2].tolist() == [27.0, 22.0]  # the map's centre cell (24, 24) + (3, -2)


@pytest.mark.parametrize(
    ("yaws", "message"),
    [
        ("0:1e12:1", "gives 1e+12 yaws, more than the 36000 searched at most"),
        ("0:inf:1", "needs three finite numbers"),
    ],
)
def test_yaw_ranges_without_a_bound_end_in_one_line(capsys, yaws, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["--map", "map.npy", "--local", "local.npy", "--yaws", yaws])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.count("\n") == 1 and message in error


def test_the_former_center_row_col_still_works_with_a_warning_that_names_around(gravel_map):
    # Mutation killed: center=(row, col) converted to around=(row, col) (unswapped): the window lands elsewhere.
    local = _noisy(_cut(gravel_map, 70, 90), 2.0)
    expected = localize(local, gravel_map, 4.0, shifts=(3, 5), around=(88, 72))
    with pytest.warns(DeprecationWarning, match=r"pass around=\(x, y\) = \(col, row\)"):
        former = localize(local, gravel_map, 4.0, shifts=(3, 5), center=(72, 88))
    torch.testing.assert_close(former.surface, expected.surface)
    torch.testing.assert_close(former.pose, expected.pose)
    assert former.pose[0, :2].round().tolist() == [90.0, 70.0] and former.shift[0].round().tolist() == [2.0, -2.0]
    with pytest.warns(DeprecationWarning, match=r"Localizer.forward\(center=\(row, col\)\) is deprecated"):
        by_module = Localizer(shifts=(3, 5))(local, gravel_map, 4.0, center=torch.tensor([[72, 88]]))
    torch.testing.assert_close(by_module.pose, expected.pose)
    with pytest.raises(TypeError, match=r"got center and around: pass around=\(x, y\) alone"):
        localize(local, gravel_map, 4.0, center=(72, 88), around=(88, 72))
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match=r"center must be \(row, col\) integers"):
        localize(local, gravel_map, 4.0, center=(72.5, 88))


def test_around_is_rounded_to_the_nearest_cell_and_given_per_sample_as_floats(gravel_map):
    # Mutation killed: the prior truncated instead of rounded (79.6 -> 79 moves the window by a cell).
    local = torch.cat([_noisy(_cut(gravel_map, 80, 80), 2.0), _noisy(_cut(gravel_map, 75, 92), 2.0, 1)])
    whole = localize(local, gravel_map, 4.0, shifts=4, around=torch.tensor([[80, 80], [90, 76]]))
    fractional = localize(local, gravel_map, 4.0, shifts=4, around=torch.tensor([[80.4, 79.6], [89.7, 76.2]]))
    torch.testing.assert_close(fractional.surface, whole.surface)
    torch.testing.assert_close(fractional.pose, whole.pose)
    assert fractional.around.tolist() == [[80.0, 80.0], [90.0, 76.0]]
    assert whole.pose[:, :2].round().tolist() == [[80.0, 80.0], [92.0, 75.0]]


def test_command_line_takes_the_former_center_with_a_note_and_refuses_both(gravel_map, tmp_path, capsys):
    np.save(tmp_path / "map.npy", gravel_map[0, 0].numpy())
    np.save(tmp_path / "local.npy", _cut(gravel_map, 84, 73)[0, 0].numpy())
    files = ["--map", str(tmp_path / "map.npy"), "--local", str(tmp_path / "local.npy"), "--variance", "4"]
    report = _command([*files, "--shifts", "8", "--center", "80", "76"])
    assert capsys.readouterr().err.strip() == "enmi-localize: --center ROW COL is deprecated: pass --around 76 80 (X Y)"
    assert (round(report["x"]), round(report["y"]), round(report["dx"]), round(report["dy"])) == (73, 84, -3, 4)
    assert report == _command([*files, "--shifts", "8", "--around", "76", "80"])
    error = _one_line_error(capsys, [*files, "--center", "80", "76", "--around", "76", "80"])
    assert "--center ROW COL is the former spelling of --around X Y: pass --around alone" in error
