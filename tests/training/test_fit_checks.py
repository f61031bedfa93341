"""enmi-fit-mask refuses every bad option and pair before the Trainer starts: one line, exit 2, no run folder left; the
mask's folder is claimed atomically, so runs started at once never share one (issue 43)."""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from enmi_torch.data.pairs import write_pairs
from enmi_torch.training.fit_checks import LOCK_FILE, MASK_RULES, check_learnable, claim_output_dir
from enmi_torch.training.mask_module import MaskFitModule
from enmi_torch.utils.options import OptionConflict, OptionError

ROOT = Path(__file__).resolve().parents[2]
SMOKE = str(ROOT / "configs" / "fit_mask_smoke.yaml")
ENVIRONMENT = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}

# Runs the command on each list of arguments in one process, each in its own folder, with the file descriptors 1 and 2
# caught per call (what a terminal would show, Lightning's log lines included); prints exit codes and outputs as JSON.
DRIVER = """
import json, os, sys, tempfile
from enmi_torch.cli.fit_mask import main
results = []
for folder, arguments in json.loads(sys.argv[1]):
    os.chdir(folder)
    out, err = tempfile.TemporaryFile(), tempfile.TemporaryFile()
    saved = os.dup(1), os.dup(2)
    os.dup2(out.fileno(), 1)
    os.dup2(err.fileno(), 2)
    try:
        main(arguments)
        code = 0
    except SystemExit as stop:
        code = stop.code
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
    texts = []
    for file in (out, err):
        file.seek(0)
        texts.append(file.read().decode())
    results.append({"code": code, "out": texts[0], "err": texts[1]})
print(json.dumps(results))
"""


def pairs_folder(root: Path, count: int, size: int, valid: bool = True) -> Path:
    generator = np.random.default_rng(0)
    items = []
    for _ in range(count):
        prior = generator.uniform(0, 255, (size, size)).astype(np.float32)
        local = prior + generator.normal(0, 5, prior.shape).astype(np.float32)
        items.append({"local": local, "prior": prior, "valid": np.full(prior.shape, valid)})
    write_pairs(root, items)
    return root


@pytest.fixture(scope="module")
def refusals(tmp_path_factory):
    """Each bad call of the command, run from a folder of its own, with what it printed and the folders it left."""
    base = tmp_path_factory.mktemp("refusals")
    (base / "binary.yaml").write_bytes(bytes(range(256)) * 4)
    (base / "a_file").write_text("a file, not a folder")
    (base / "a_folder.npy").mkdir()
    folders = {
        "two": pairs_folder(base / "pairs" / "two", 2, 16),
        "masked": pairs_folder(base / "pairs" / "masked", 8, 16, valid=False),
        "one_pixel": pairs_folder(base / "pairs" / "one_pixel", 8, 1),
        "four_pixels": pairs_folder(base / "pairs" / "four_pixels", 8, 4),
    }
    cases = {
        "lr": ["--model.lr", "-1"],
        "smoothness": ["--model.smoothness", "-1"],
        "bins": ["--model.bins", "1"],
        "value_range": ["--model.value_range", "[5, 5]"],
        "train_pairs": ["--data.train_pairs", "1"],
        "two_pairs": ["--data.root", str(folders["two"])],
        "masked": ["--data.root", str(folders["masked"])],
        "one_pixel": ["--data.root", str(folders["one_pixel"])],
        "four_pixels": ["--data.root", str(folders["four_pixels"])],
        "shift": ["--model.localization_shift", "-1"],
        "crop": ["--model.localization_shift", "20"],
        "grid": ["--model.localization_grid", "[0.25, -4]"],
        "noise": ["--model.localization_noise", "[1, 0]"],
        "noise_twice": ["--model.localization_noise", "[16, 16.0]"],
        "noise_empty": ["--model.localization_noise", "[]"],
        "degree": ["--model.degree", "3"],
        "analytic": ["--model.form", "perspective", "--model.analytic_variance", str(base / "a_folder.npy")],
        "perspective": ["--model.form", "perspective", "--data.root", str(folders["two"])],
        "config": ["--config", str(base / "binary.yaml")],
        "root_dir": ["--trainer.default_root_dir", str(base / "a_file")],
        "save_dir": ["--trainer.logger.init_args.save_dir", str(base / "a_file" / "runs")],
        "output_dir": ["--output_dir", str(base / "a_file")],
        "ckpt_path": ["--ckpt_path", str(base / "a_folder.npy")],
    }
    calls = []
    for name, arguments in cases.items():
        (base / "work" / name).mkdir(parents=True)
        calls.append([str(base / "work" / name), ["--config", SMOKE, *arguments]])
    completed = subprocess.run(
        [sys.executable, "-c", DRIVER, json.dumps(calls)],
        cwd=base,
        env=ENVIRONMENT,
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    return {
        name: {**result, "left": sorted(path.name for path in (base / "work" / name).iterdir())}
        for name, result in zip(cases, json.loads(completed.stdout), strict=True)
    }


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("lr", "--model.lr must be a finite number > 0, got -1.0"),
        ("smoothness", "--model.smoothness must be a finite number >= 0, got -1.0"),
        ("bins", "--model.bins must be an int >= 2, got 1"),
        ("value_range", "--model.value_range must be finite with low < high, got (5.0, 5.0)"),
        (
            "train_pairs",
            "--data.train_pairs 1: no pixel is valid in two training pairs or more: nothing to learn a variance from; "
            "pass --data.train_pairs 2 or more",
        ),
        ("two_pairs", "holds 2 pair(s), 1 held out (--data.val_fraction 0.05) and 1 to train on: no pixel is valid"),
        (
            "masked",
            "holds 8 pair(s), 1 held out (--data.val_fraction 0.05) and 7 to train on: no pixel is valid in two",
        ),
        (
            "one_pixel",
            "the pairs are 1x1 pixels: too small for the held-out search, which searches a crop of up to "
            "--model.localization_crop 32 pixels inside a border of --model.localization_shift 2 pixels on each side; "
            "pass --model.localization_pairs 0 (no held-out search)",
        ),
        (
            "four_pixels",
            "the pairs are 4x4 pixels: too small for the held-out search, which searches a crop of up to "
            "--model.localization_crop 32 pixels inside a border of --model.localization_shift 2 pixels on each side; "
            "pass --model.localization_shift 1 or less, or --model.localization_pairs 0 (no held-out search)",
        ),
        ("shift", "--model.localization_shift must be an int >= 1, got -1"),
        ("crop", "the pairs are 32x32 pixels: too small for the held-out search"),
        ("grid", "--model.localization_grid must be finite factors > 0, got [0.25, -4.0]"),
        ("noise", "--model.localization_noise must be null (levels read from the data) or finite factors > 0, got"),
        ("noise_twice", "--model.localization_noise must be distinct factors, got [16.0, 16.0]"),
        ("noise_empty", "--model.localization_noise must be null (levels read from the data) or finite factors > 0"),
        (
            "degree",
            "--model.degree 3 has no effect with --model.form pixel: it is the degree of the radial form's polynomial; "
            "drop it or pass --model.form radial",
        ),
        ("analytic", "--model.analytic_variance must name an .npy file, got the folder"),
        (
            "perspective",
            "--model.form perspective needs an analytic variance map when the data has no known field: pass "
            "--model.analytic_variance MAP.npy",
        ),
        ("config", "--config '"),
        ("root_dir", "--trainer.default_root_dir must be a folder, got"),
        ("save_dir", "--trainer.logger.init_args.save_dir must be a folder, got"),
        ("output_dir", "--output_dir must be a folder, got"),
        ("ckpt_path", "--ckpt_path must be a checkpoint file, got the folder"),
    ],
)
def test_a_bad_option_or_pair_is_one_line_before_anything_else_and_leaves_no_run_folder(refusals, case, message):
    result = refusals[case]
    assert result["code"] == 2 and result["out"] == "", result
    assert result["err"].count("\n") == 1 and result["err"].startswith("enmi-fit-mask: error: "), result["err"]
    assert message in result["err"], result["err"]
    assert "runs" not in result["left"], result["left"]  # no run folder, nor the folders made for it
    if case == "config":
        assert "is not UTF-8 text (a binary file?): pass a YAML file" in result["err"]


def test_the_model_refuses_its_options_when_it_is_made(tmp_path):
    """The library's own spelling of the same checks (the command re-spells each option as its flag)."""
    with pytest.raises(ValueError, match=r"^lr must be a finite number > 0, got 0$"):
        MaskFitModule(lr=0)
    with pytest.raises(ValueError, match=r"^smoothness must be a finite number >= 0, got inf$"):
        MaskFitModule(smoothness=float("inf"))
    with pytest.raises(OptionError) as refusal:
        MaskFitModule(shape=(6, 40), localization_shift=3)
    assert str(refusal.value) == (
        "the pairs are 6x40 pixels: too small for the held-out search, which searches a crop of up to "
        "localization_crop=32 pixels inside a border of localization_shift=3 pixels on each side; pass "
        "localization_shift=2 or less, or localization_pairs=0 (no held-out search)"
    )
    assert MaskFitModule(shape=(6, 40), localization_shift=2).hparams.localization_shift == 2  # 2 pixels left
    assert MaskFitModule(shape=(5, 40), localization_shift=2).shape == (5, 40)  # 1 pixel left: the least it takes
    assert MaskFitModule(shape=(6, 40), localization_shift=3, localization_pairs=0).shape == (6, 40)
    with pytest.raises(OptionConflict, match=r"analytic_variance='m\.npy' has no effect with form='radial'"):
        MaskFitModule(form="radial", analytic_variance="m.npy")
    assert [rule.option for rule in MASK_RULES] == ["degree", "analytic_variance"]
    assert MaskFitModule(form="radial", degree=6).hparams.degree == 6


def _holder(folder: Path) -> subprocess.Popen:
    """Another process that claims ``folder`` and holds it until it is killed."""
    code = (
        "import sys; from pathlib import Path; from enmi_torch.training.fit_checks import claim_output_dir; "
        f"claim_output_dir(Path({str(folder)!r}), False); print('held', flush=True); sys.stdin.read()"
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", code], env=ENVIRONMENT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert holder.stdout.readline() == "held\n"
    return holder


def test_an_output_folder_held_by_another_process_is_refused_and_freed_when_it_dies(tmp_path):
    folder = tmp_path / "made" / "out"
    holder = _holder(folder)
    try:
        with pytest.raises(ValueError, match=r"^--output_dir '.*out' is being written by another run"):
            claim_output_dir(folder, False)
    finally:
        holder.send_signal(signal.SIGKILL)  # killed without a chance to clean up: the lock goes with it
        holder.wait(timeout=60)
    claim = claim_output_dir(folder, False)
    with pytest.raises(ValueError, match="is being written by another run"):  # a second claim of this process too
        claim_output_dir(folder, True)
    claim.release()
    claim.release()  # once is enough
    assert not (folder / LOCK_FILE).exists()
    (folder / "variance_mask.pt").write_bytes(b"a finished mask")
    with pytest.raises(FileExistsError, match=r"already holds variance_mask\.pt from an earlier run"):
        claim_output_dir(folder, False)
    claim_output_dir(folder, True).release()  # --overwrite true
    assert (folder / "variance_mask.pt").read_bytes() == b"a finished mask"


def test_a_claim_that_is_refused_or_released_unused_leaves_no_folder_it_made(tmp_path):
    claim_output_dir(tmp_path / "a" / "b" / "out", False).release()
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "kept").mkdir()
    claim = claim_output_dir(tmp_path / "kept" / "out", False)
    (tmp_path / "kept" / "out" / "variance_mask.npy").write_bytes(b"written")
    claim.release()
    assert (tmp_path / "kept" / "out" / "variance_mask.npy").is_file()  # a folder with the run's files stays


def test_two_runs_started_at_once_with_one_output_dir_never_share_it(tmp_path):
    output = tmp_path / "shared"
    command = [sys.executable, str(ROOT / "train" / "fit_mask.py"), "--config", SMOKE, "--output_dir", str(output)]
    command += ["--model.localization_pairs", "0", "--trainer.max_epochs", "1"]
    processes = [
        subprocess.Popen(command, cwd=tmp_path, env=ENVIRONMENT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        for _ in range(2)
    ]
    results = [(process.wait(timeout=600), *(text.decode() for text in process.communicate())) for process in processes]
    codes = sorted(code for code, _, _ in results)
    assert codes == [0, 2], [err[-500:] for _, _, err in results]
    (refused_err,) = [err for code, _, err in results if code == 2]
    assert refused_err.count("\n") == 1, refused_err  # refused before training: no Lightning line
    assert "is being written by another run" in refused_err or "already holds" in refused_err, refused_err
    (winner_out,) = [out for code, out, _ in results if code == 0]
    summary = json.loads((output / "summary.json").read_text())
    assert summary["files"]["npy"] == str(output / "variance_mask.npy")
    assert sorted(path.name for path in (tmp_path / "runs" / "fit_mask").iterdir()) == ["lidar_0"]  # one run folder
    assert str(output) in winner_out and not (output / LOCK_FILE).exists()


def test_a_pixel_valid_in_two_training_pairs_is_enough_to_learn_from():
    import types

    import torch

    def data(*masks, held_out=1):
        pairs = [{"valid": torch.tensor(mask)} for mask in masks]
        return types.SimpleNamespace(train_set=pairs, val_set=[None] * held_out)

    folder = {"root": "pairs", "val_fraction": 0.05}
    check_learnable(data([True, False], [True, False]), folder)  # the first pixel, in both
    check_learnable(data([False, True], [True, False], [False, True]), {"root": None})
    with pytest.raises(ValueError, match=r"1 to train on: no pixel is valid in two .*; give it more pairs$"):
        check_learnable(data([True, True]), folder)
    with pytest.raises(ValueError, match=r"and 2 to train on: .*; their valid/ masks must overlap$"):
        check_learnable(data([True, False], [False, True]), folder)
    with pytest.raises(ValueError, match=r"^--data.train_pairs 3: no pixel .*; pass --data.train_pairs 2 or more$"):
        check_learnable(data([True, False], [False, True], [False, False]), {"root": None})
