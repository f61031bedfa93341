"""The fit-mask command on a user's own pairs: it finishes, keeps its mask, fails fast and cleanly (issues 34, 35)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from enmi_torch.cli.fit_mask import main
from enmi_torch.data.pairs import write_pairs
from enmi_torch.data.synthetic import SyntheticPairs
from enmi_torch.data.truth import make_truth
from enmi_torch.training.logger import next_version
from enmi_torch.training.mask_module import MaskFitModule
from enmi_torch.variance import LearnedVariance

ROOT = Path(__file__).resolve().parents[2]
SMOKE = str(ROOT / "configs" / "fit_mask_smoke.yaml")


@pytest.fixture(autouse=True)
def _command_line(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["fit_mask.py"])  # main(args) stands for the command line, not pytest's
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def write_folder(root: Path, pairs: int = 80, size: int = 32, amplify: float = 1.0, scale: float = 1.0) -> Path:
    """Pairs in the folder format; ``amplify`` scales each residual and clips to 0..255.999 like a camera."""
    truth = make_truth("lidar", (size, size), 12.0)
    items = []
    for item in SyntheticPairs(truth, pairs, seed=0):
        local = (item["prior"] + amplify * (item["local"] - item["prior"])).clamp(0, 255.999)
        items.append({"local": local * scale, "prior": item["prior"] * scale, "valid": item["valid"]})
    write_pairs(root, items)
    return root


@pytest.fixture(scope="module")
def strong_noise_pairs(tmp_path_factory) -> Path:
    """Pairs with 16 times the lidar-like noise, clipped: the held-out x16 and x32 sets leave value_range far."""
    return write_folder(tmp_path_factory.mktemp("pairs") / "strong", amplify=16.0)


def command(tmp_path, *arguments):
    return ["--config", SMOKE, "--trainer.logger.init_args.save_dir", str(tmp_path), *arguments]


def exit_code(arguments) -> int:
    try:
        main(arguments)
    except SystemExit as exit_info:
        return exit_info.code
    return 0


@pytest.mark.slow
def test_strong_clipped_noise_runs_to_the_end_and_writes_its_mask(tmp_path, strong_noise_pairs, capsys):
    """Levels read from pairs whose noise is already strong (the default), by the command, to the end."""
    arguments = command(
        tmp_path, "--data.root", str(strong_noise_pairs), "--output_dir", str(tmp_path / "out"),
        "--model.localization_noise", "null", "--model.localization_shift", "4", "--data.val_fraction", "0.2",
    )  # fmt: skip
    assert exit_code(arguments) == 0, capsys.readouterr().err
    mask = LearnedVariance.load(tmp_path / "out" / "variance_mask.pt")
    assert mask.shape == (32, 32) and (tmp_path / "out" / "summary.json").is_file()
    printed = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    calibration, levels = summary["localization_calibration"], summary["localization_levels"]
    assert calibration["pairs"] == 4 and list(summary["localization"]) == ["level_easy", "level_hard"]
    assert levels == {"level_easy": calibration["easy"], "level_hard": calibration["hard"]}
    assert levels["level_easy"] == float(f"{levels['level_hard'] / 4:.2g}")
    factors, best = calibration["factors"], calibration["best"]
    if calibration["bracketed"] == "yes":  # the hard level lies between the last factor at half or above and the next
        low = max(factor for factor, share in zip(factors, best, strict=True) if share >= 0.5)
        assert low <= levels["level_hard"] <= 2 * low and best[factors.index(2 * low)] < 0.5
    assert "    best share " + "".join(f"{share:>7.2f}" for share in best) in printed
    assert (
        f"    level_hard x{levels['level_hard']:g}: " in printed
        and f"    level_easy x{levels['level_easy']:g}: " in printed
    )


def test_held_out_sets_are_clipped_to_the_value_range_as_a_sensor_clips():
    model = MaskFitModule(shape=(24, 24), localization_shift=2, localization_crop=16, localization_noise=(1, 32))
    generator = torch.Generator().manual_seed(0)
    prior = torch.rand(2, 1, 24, 24, generator=generator) * 256
    local = (prior + 40 * torch.randn(2, 1, 24, 24, generator=generator)).clamp(0, 255.999)
    sets = model.held_out_sets(local, prior, torch.ones_like(local, dtype=torch.bool))
    strong = sets["noise_x32"][0]
    assert float(strong.min()) >= 0.0 and float(strong.max()) <= 256.0
    assert float((strong == 0).float().mean()) > 0.2  # clipped, not squeezed
    window = (..., slice(2, 22), slice(2, 22))
    torch.testing.assert_close(sets["noise_x1"][0], local[window])  # the data as it is


class EvaluationFails(RuntimeError):
    pass


def test_the_mask_is_written_before_evaluation_starts(tmp_path, monkeypatch, capsys):
    """An error in the held-out evaluation cannot lose the trained mask: it is on disk, and the error says where."""

    def failing(self, *args):
        raise ValueError("evaluation went wrong")

    monkeypatch.setattr(MaskFitModule, "_localize", failing)
    output_dir = tmp_path / "out"
    assert exit_code(command(tmp_path, "--output_dir", str(output_dir), "--trainer.check_val_every_n_epoch", "2")) == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith("enmi-fit-mask: error: evaluation went wrong") and str(output_dir) in error
    mask = LearnedVariance.load(output_dir / "variance_mask.pt")
    assert mask.shape == (32, 32) and torch.isfinite(mask.variance_map()).any()


@pytest.mark.parametrize(
    ("scale", "hint"),
    [(1 / 256, '--model.value_range "[0, 1]"'), (256.0, '--model.value_range "[0, 65536]"')],
)
def test_pairs_outside_the_value_range_are_refused_before_training_in_the_commands_spelling(
    tmp_path, capsys, scale, hint
):
    pairs = write_folder(tmp_path / "pairs", pairs=24, size=16, scale=scale)
    runs = tmp_path / "runs"
    assert exit_code(command(runs, "--data.root", str(pairs))) == 2
    captured = capsys.readouterr()
    error = captured.err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("enmi-fit-mask: error: ") and hint in error[0]
    assert "value_range=(" not in error[0] and "Epoch" not in captured.out + captured.err  # before any training
    assert not runs.exists()


def test_a_run_that_fails_before_its_first_epoch_leaves_no_run_folder(tmp_path, capsys):
    pairs = write_folder(tmp_path / "pairs", pairs=24, size=16)
    for path in (pairs / "local").glob("*.npy"):
        image = np.load(path)
        image[3, 3] = np.nan  # every pair: the first one read fails
        np.save(path, image)
    runs = tmp_path / "runs"
    assert exit_code(command(runs, "--data.root", str(pairs))) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "NaN" in error[0]
    assert not runs.exists()  # neither the run folder nor the folders made for it


def test_default_root_dir_moves_logs_and_checkpoints(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    arguments = ["--config", SMOKE, "--model.localization_pairs", "0", "--trainer.default_root_dir", "elsewhere"]
    assert exit_code(arguments) == 0
    assert not (tmp_path / "runs").exists()
    assert (tmp_path / "elsewhere" / "fit_mask" / "lidar_0" / "checkpoints" / "last.ckpt").is_file()
    assert (tmp_path / "elsewhere" / "fit_mask" / "lidar_0" / "mask" / "variance_mask.pt").is_file()


def test_run_folders_are_chosen_atomically(tmp_path):
    """Each call takes its folder, as three runs started at once must: none is handed out twice."""
    names = [next_version(tmp_path, "lidar") for _ in range(3)]
    assert names == ["lidar_0", "lidar_1", "lidar_2"] and all((tmp_path / name).is_dir() for name in names)


def test_three_runs_started_at_once_take_three_folders(tmp_path):
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}
    arguments = [sys.executable, str(ROOT / "train" / "fit_mask.py"), "--config", SMOKE]
    arguments += ["--model.localization_pairs", "0", "--trainer.max_epochs", "1"]
    processes = [
        subprocess.Popen(arguments, cwd=tmp_path, env=environment, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        for _ in range(3)
    ]
    results = [process.communicate(timeout=600) for process in processes]
    assert [process.returncode for process in processes] == [0, 0, 0], [err.decode()[-500:] for _, err in results]
    folders = sorted(path.name for path in (tmp_path / "runs" / "fit_mask").iterdir())
    assert folders == ["lidar_0", "lidar_1", "lidar_2"]
    assert all((tmp_path / "runs" / "fit_mask" / name / "mask" / "variance_mask.pt").is_file() for name in folders)


@pytest.mark.parametrize("content", ["epoch 3 loss 0.5\n", "hello\n", "not a checkpoint\n"])  # IndexError, KeyError
def test_a_text_file_as_checkpoint_ends_in_one_line(tmp_path, capsys, content):
    text = tmp_path / "notes.txt"
    text.write_text(content)
    assert exit_code(command(tmp_path, "--ckpt_path", str(text))) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("enmi-fit-mask: error: --ckpt_path") and str(text) in error[0]


def test_an_output_dir_that_is_a_file_is_refused_before_training(tmp_path, capsys):
    output = tmp_path / "taken"
    output.write_text("a file")
    assert exit_code(command(tmp_path / "runs", "--output_dir", str(output))) == 2
    captured = capsys.readouterr()
    error = captured.err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("enmi-fit-mask: error: --output_dir") and "file" in error[0]
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").rglob("*.tfevents*"))


def test_a_mistake_prints_nothing_before_its_line(tmp_path):
    """No Lightning banner ("GPU available", "Seed set") before the one line, whichever check refuses."""
    text = tmp_path / "notes.txt"
    text.write_text("epoch 3 loss 0.5\n")
    output = tmp_path / "taken"
    output.write_text("a file")
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    for arguments in (["--ckpt_path", str(text)], ["--output_dir", str(output)]):
        completed = subprocess.run(
            [sys.executable, str(ROOT / "train" / "fit_mask.py"), "--config", SMOKE, *arguments],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=300,
            env=environment,
        )
        assert completed.returncode == 2 and completed.stdout == ""
        assert completed.stderr.count("\n") == 1 and completed.stderr.startswith("enmi-fit-mask: error: ")
