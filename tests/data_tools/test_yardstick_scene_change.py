import csv
import json

import numpy as np
import pytest
import torch

from data_tools.experiments.yardstick import scene_change


@pytest.fixture(scope="module")
def yardstick():
    return scene_change


def _crop(trials, index, size):
    row, col = trials.truth[index].tolist()
    return trials.window[index, 0, row : row + size, col : col + size]


def test_noise_only_trials_cut_the_captured_image_at_the_truth(yardstick):
    trials = yardstick.make_trials("same", 5, 3)
    again = yardstick.make_trials("same", 5, 3)
    assert torch.equal(trials.clean, again.clean) and torch.equal(trials.draws, again.draws)
    assert trials.window.shape == (5, 1, 88, 88) and trials.clean.shape == (5, 1, 64, 64)
    for index in range(5):
        assert torch.equal(trials.clean[index, 0], _crop(trials, index, 64))
    shifts = trials.truth - yardstick.RADIUS
    assert bool((shifts.abs() < yardstick.RADIUS).all()) and len({tuple(s) for s in shifts.tolist()}) > 1


def test_nonmonotonic_trials_are_the_map_through_the_response(yardstick):
    trials = yardstick.make_trials("nonmonotonic", 3, 5)
    for index in range(3):
        expected = 255 * (2 * _crop(trials, index, 64) / 255 - 1).abs() ** 0.8
        torch.testing.assert_close(trials.clean[index, 0], expected)


def test_changed_trials_share_poses_and_differ_from_the_map(yardstick):
    same, changed = yardstick.make_trials("same", 4, 3), yardstick.make_trials("occluders@0.5", 4, 3)
    assert torch.equal(same.truth, changed.truth) and torch.equal(same.window, changed.window)
    for index in range(4):
        difference = (changed.clean[index, 0] - _crop(changed, index, 64)).abs()
        assert 0.05 < float((difference > 1).double().mean()) < 0.9


def test_real_pairs_are_read_from_their_folders(yardstick, tmp_path):
    folder = tmp_path / "another-date" / "place-1"
    (tmp_path / "another-date" / "other-1").mkdir(parents=True)  # no arrays: not a pair
    folder.mkdir(parents=True)
    generator = np.random.default_rng(0)
    reference = generator.uniform(0, 255, (100, 120)).astype(np.float32)
    np.save(folder / "reference.npy", reference)
    np.save(folder / "captured.npy", 255 - reference)
    assert yardstick.real_cases(tmp_path) == ["real:another-date/place"]
    (folder / "meta.json").write_text('{"dataset": "survey"}')
    assert yardstick.real_cases(tmp_path) == ["real:another-date/survey"]
    assert yardstick.pair_folders(tmp_path, "another-date") == [folder]
    trials = yardstick.make_trials("real:another-date/survey", 3, 1, tmp_path)
    for index in range(3):
        torch.testing.assert_close(trials.clean[index, 0], 255 - _crop(trials, index, 64))


@pytest.mark.parametrize("case", ["fog@0.5", "tone@2", "tone", "tone@0", "monotonic"])
def test_bad_cases_are_refused(yardstick, case):
    with pytest.raises(ValueError, match="case"):
        yardstick.parse_case(case)


def test_a_tiny_run_writes_its_tables(yardstick, tmp_path, capsys):
    methods = ["ECR true", "ECR today", "ECR uniform x1", "ECR uniform x4", "NMI", "ECR learned"]
    output = tmp_path / "run"
    learned = tmp_path / "mask.npy"
    np.save(learned, np.full((64, 64), 900.0, dtype=np.float32))
    argv = ["--trials", "2", "--cases", "same", "tone@0.5", "--sensors", "camera-like", "--levels", "60"]
    argv += ["--noise-only-sensors", "paper-camera", "--same-levels", "--methods", *methods]
    argv += ["--learned-mask", str(learned), "--output", str(output), "--data", str(tmp_path / "none")]
    yardstick.main(argv)
    with (output / "results.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 2 * len(methods)
    assert {(row["case"], row["sensor"]) for row in rows} == {("same", "paper-camera"), ("tone@0.5", "camera-like")}
    assert all(len(row["outcomes"]) == 2 and set(row["outcomes"]) <= {"0", "1"} for row in rows)
    assert all(len(row["tau2"].split()) == (2 if row["method"] in ("ECR true", "ECR learned") else 0) for row in rows)
    report = (output / "report.md").read_text()
    assert "| tone@0.5 | camera-like | 60 |" in report and "ECR best uniform" in report
    assert "ECR learned against ECR true" in report and "| ECR true | scene change |" in report
    capsys.readouterr()
    yardstick.main(["--report", "--output", str(output)])
    assert capsys.readouterr().out.strip() == report.strip()


def test_a_learned_mask_against_the_true_map_alone_reports_that_control_only(yardstick, tmp_path, capsys):
    output, learned = tmp_path / "run", tmp_path / "mask.npy"
    np.save(learned, np.full((64, 64), 900.0, dtype=np.float32))
    argv = ["--trials", "2", "--cases", "tone@0.5", "--sensors", "camera-like", "--levels", "60", "--same-levels"]
    argv += ["--noise-only-sensors", "camera-like", "--methods", "ECR learned", "ECR true", "--learned-mask"]
    yardstick.main([*argv, str(learned), "--output", str(output), "--data", str(tmp_path / "none")])
    report = (output / "report.md").read_text()
    assert "- minus ECR true:" in report and "- minus ECR today" not in report
    capsys.readouterr()


def test_methods_are_score_objects_with_their_variances(yardstick):
    from enmi_torch import ECR
    from enmi_torch.scores.ecr import default_model_variance

    assert yardstick.METHODS["ECR true"] == (ECR(bins=32), "true")
    assert ECR(bins=32).model_variance == "estimate"
    assert yardstick.METHODS["ECR today"] == (ECR(bins=32, model_variance=default_model_variance(32, (0, 256))), "true")
    assert yardstick.METHODS["ECR uniform x0.25"] == (ECR(bins=32), 0.25)
    assert "ECR learned" not in yardstick.DEFAULT_METHODS


def test_real_folders_split_each_dataset_in_halves(yardstick, tmp_path):
    for dataset, count in (("alpha", 3), ("beta", 2)):
        for index in range(count):
            folder = tmp_path / "another-date" / f"{dataset}-{index}"
            folder.mkdir(parents=True)
            np.save(folder / "reference.npy", np.zeros((90, 90), np.float32))
            np.save(folder / "captured.npy", np.zeros((90, 90), np.float32))
    names = lambda half: [f.name for f in yardstick.pair_folders(tmp_path, "another-date", half)]  # noqa: E731
    assert names("even") == ["alpha-0", "alpha-2", "beta-0"] and names("odd") == ["alpha-1", "beta-1"]
    assert sorted(names("even") + names("odd")) == names("all")


def test_command_line_mistakes_exit_with_2(yardstick, tmp_path, capsys):
    for argv in (
        ["--cases", "fog@1"],
        ["--trials", "1"],
        ["--cases", "real:nowhere", "--data", str(tmp_path)],
        ["--methods", "ECR learned"],
    ):
        with pytest.raises(SystemExit) as exit_info:
            yardstick.main([*argv, "--output", str(tmp_path / "out")])
        assert exit_info.value.code == 2
    assert "case" in capsys.readouterr().err


def test_noise_is_clipped_as_a_sensor_saturates(yardstick):
    trials = yardstick.make_trials("same", 4, 2)
    clipped, variance = yardstick.noisy(trials, "camera-like", 200.0)
    free, same_variance = yardstick.noisy(trials, "camera-like", 200.0, clip=False)
    assert torch.equal(variance, same_variance)
    assert float(clipped.min()) == 0.0 and float(clipped.max()) == 255.999
    assert bool(((free < 0) | (free > 255.999)).any())
    inside = (free >= 0) & (free <= 255.999)
    assert torch.equal(clipped[inside], free[inside])


def test_calibration_methods_hold_correlation_and_the_linear_response(yardstick):
    assert {"NCC", "ECR linear true", "ECR linear uniform", "ECR binned true", "ECR true"} <= set(
        yardstick.CALIBRATION_METHODS
    )
    assert set(yardstick.CALIBRATION_METHODS) <= set(yardstick.DEFAULT_METHODS)
    assert yardstick.METHODS["ECR linear uniform"] == (yardstick.ECR(bins=32, response="linear"), 1.0)
    assert yardstick.METHODS["ECR binned true"] == (yardstick.ECR(bins=32, response="binned"), "true")


def test_l50_is_set_by_the_best_of_all_methods(yardstick, monkeypatch):
    """NCC succeeds up to level 256, the information scores only up to 16: L50 follows NCC when NCC is calibrated."""

    def fake_run_methods(trials, sensor, level, methods, learned=None, clip=True):
        limit = {"NCC": 256.0}
        count = trials.truth.shape[0]
        return {m: (torch.full((count,), level <= limit.get(m, 16.0)), []) for m in methods}

    monkeypatch.setattr(yardstick, "run_methods", fake_run_methods)
    every = yardstick.calibrate("same", "camera-like", 4, 0, None)
    information = yardstick.calibrate("same", "camera-like", 4, 0, None, yardstick.INFORMATION_METHODS)
    assert every["leader"] == "NCC" and 256 <= every["L50"] < 512 and every["rates"]["NCC"][6] == 1.0
    assert information["leader"] == "ECR true" and 16 <= information["L50"] < 32
    assert every["clip"] and every["methods"] == list(yardstick.CALIBRATION_METHODS)


def test_an_earlier_calibration_is_reused_only_for_the_same_methods_and_clipping(yardstick, tmp_path, monkeypatch):
    calls = []

    def fake_calibrate(case, sensor, trials, seed, data, methods=(), clip=True):
        calls.append((case, sensor))
        return {"case": case, "sensor": sensor, "L50": 99.0, "bracketed": "yes", "best_rates": [1.0, 0.2]}

    monkeypatch.setattr(yardstick, "calibrate", fake_calibrate)
    earlier = tmp_path / "calibration.json"
    entry = {"case": "same", "sensor": "camera-like", "L50": 50.0, "bracketed": "yes", "best_rates": [1.0]}
    argv = ["--cases", "same", "--noise-only-sensors", "camera-like", "--calibrate-only", "--data", str(tmp_path)]
    current = entry | {"methods": list(yardstick.CALIBRATION_METHODS), "clip": True}
    for stored, extra, expected in (
        (entry, [], 1),  # written before issue 33: information scores, unclipped
        (current, [], 0),
        (current, ["--no-clip"], 1),
    ):
        calls.clear()
        earlier.write_text(json.dumps([stored]))
        yardstick.main([*argv, *extra, "--calibration", str(earlier), "--output", str(tmp_path / "run")])
        assert len(calls) == expected


def test_same_on_real_pairs_is_the_reference_photograph_against_itself(yardstick, tmp_path):
    folder = tmp_path / "another-date" / "place-1"
    folder.mkdir(parents=True)
    reference = np.random.default_rng(1).uniform(0, 255, (100, 120)).astype(np.float32)
    np.save(folder / "reference.npy", reference)
    np.save(folder / "captured.npy", 255 - reference)
    assert yardstick.is_noise_only("same:another-date") and yardstick.group_of("same:another-date") == "noise only"
    trials = yardstick.make_trials("same:another-date", 3, 1, tmp_path)
    for index in range(3):
        torch.testing.assert_close(trials.clean[index, 0], _crop(trials, index, 64))


def test_the_report_pairs_every_method_with_ecr_true(yardstick, tmp_path, capsys):
    output = tmp_path / "run"
    argv = ["--trials", "3", "--cases", "same", "--noise-only-sensors", "lidar-like", "--levels", "40"]
    argv += ["--same-levels", "--methods", "ECR true", "ECR binned true", "ECR linear uniform", "NCC"]
    yardstick.main([*argv, "--output", str(output), "--data", str(tmp_path / "none")])
    report = (output / "report.md").read_text()
    section = report.split("each method minus ECR true")[1]
    assert "| ECR binned true | ECR linear uniform | NCC |" in section.splitlines()[2]
    assert "| same | lidar-like | 40 | " in section and "| all, pooled | 1 cells |" in section
    capsys.readouterr()


def test_the_capped_and_regional_variances_are_what_they_say(yardstick):
    from enmi_torch.scores.ecr import ecr_model_variance

    trials = yardstick.make_trials("occluders@0.5", 3, 4)
    context = next(yardstick._contexts(trials, "lidar-like", 150.0))
    capped = yardstick._variance(context, "capped")
    assert float(capped.max()) == pytest.approx(255.999**2 / 4)
    assert torch.equal(capped[context.variance < 255.999**2 / 4], context.variance[context.variance < 255.999**2 / 4])
    # Read at the truth, the map is the regional misfit of each captured image against its own section, by a loop.
    at_truth = yardstick._variance(context, "regional at truth")
    assert at_truth.shape == (3, 1, 64, 64)
    for index in range(3):
        row, col = trials.truth[index].tolist()
        section = context.window[index : index + 1, :, row : row + 64, col : col + 64]
        misfit = ecr_model_variance(context.local[index : index + 1], section, context.variance, misfit="regional")
        torch.testing.assert_close(at_truth[index, 0], context.variance[0, 0] + misfit[0].float())
    # Read at the default surface's peak: the same map wherever that peak is the truth.
    at_peak = yardstick._variance(context, "regional at peak")
    surface = yardstick.METHODS["ECR true"][0].surface(context.local, context.window, context.variance).score
    peak = surface.flatten(1).argmax(1)
    found = (peak // surface.shape[-1] == trials.truth[:, 0]) & (peak % surface.shape[-1] == trials.truth[:, 1])
    assert bool(found.any()), "the fixture needs a trial the default finds"
    torch.testing.assert_close(at_peak[found], at_truth[found])
