import io
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from _pickle_payload import EXECUTED, Payload
from lightning.pytorch import Callback, Trainer
from lightning.pytorch.callbacks import ModelCheckpoint
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from enmi_torch import NCC
from enmi_torch.cli.fit_mask import main
from enmi_torch.data import PairDataModule
from enmi_torch.training.fit_mask import fit_mask
from enmi_torch.training.held_out import amplified, localization_trials
from enmi_torch.training.mask_module import MaskFitModule
from enmi_torch.variance import LearnedVariance, empirical_variance

ROOT = Path(__file__).resolve().parents[2]
SMOKE = str(ROOT / "configs" / "fit_mask_smoke.yaml")


@pytest.fixture(autouse=True)
def _command_line(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["fit_mask.py"])  # main(args) stands for the command line, not pytest's
    threads = torch.get_num_threads()  # the command sets torch_threads for its process
    yield
    torch.set_num_threads(threads)


def run(tmp_path, *overrides):
    return fit_mask(["--config", SMOKE, "--trainer.logger.init_args.save_dir", str(tmp_path), *overrides])


def test_smoke_run_writes_mask_files_and_dashboards(tmp_path, capsys):
    summary = run(tmp_path, "--trainer.enable_progress_bar", "true")
    printed, logged = capsys.readouterr()
    assert "mask_error=" in printed and "v_num" not in printed and "train/loss" not in printed  # the progress bar
    summary_lines = printed[printed.index("Variance mask learned") :].splitlines()
    assert summary_lines[1].startswith("  relative RMS error vs the paper's empirical mask")
    assert any(line.startswith("  not converged after 2 epochs") for line in summary_lines)
    assert "tensorboard --logdir" in printed and "Tip" not in logged and "deprecated" not in logged
    assert summary_lines[-5:] == [
        "Use the mask, with the library's default score first:",
        f'  mask = LearnedVariance.load("{summary["files"]["pt"]}")',
        "  localize(captured, prior_map, mask)   # ECR(), localize's default score",
        "  ECRLoss(variance_model=mask)          # its loss (registration, training)",
        "  ENMILoss(variance_model=mask)         # ENMI, the paper's score",
    ]
    files = {suffix: Path(path) for suffix, path in summary["files"].items()}
    assert all(path.is_file() for path in files.values())
    assert json.loads((files["pt"].parent / "summary.json").read_text())["train_pairs"] == 64
    from_pt, from_npy = LearnedVariance.load(files["pt"]), LearnedVariance.load(files["npy"])
    torch.testing.assert_close(from_pt.variance_map().float(), from_npy.variance_map().float(), equal_nan=True)
    assert Path(summary["last_checkpoint"]).is_file()

    events = EventAccumulator(summary["log_dir"], size_guidance={"images": 0, "histograms": 0, "scalars": 0})
    events.Reload()
    tags = events.Tags()
    methods = ["ecr_learned", "ecr_true", "ecr_uniform", "ecr_best_uniform"]
    methods += ["enmi_learned", "enmi_true", "enmi_uniform", "enmi_best_uniform", "nmi", "ncc"]
    held_out = ["noise_x1", "noise_x4"]  # the smoke config's levels, by hand
    expected_scalars = {"train/nll", "val/nll", "mask/rel_rms_vs_empirical", "mask/rel_rms_vs_truth"}
    expected_scalars |= {"mask/empirical_rel_rms_vs_truth", "speed/pairs_per_second"}
    expected_scalars |= {f"localization/{name}/{method}" for name in held_out for method in methods}
    expected_scalars |= {f"localization_z/{name}/{method}" for name in held_out for method in methods}
    assert set(tags["scalars"]) - expected_scalars == {"lr-Adam"}  # one training loss, no epoch, no hp_metric
    assert {"masks", "localization"} <= set(tags["images"]) and {"residuals/raw", "residuals/standardised"} <= set(
        tags["histograms"]
    )
    image = events.Images("masks")[-1]
    assert 1.6 < image.width / image.height < 2.2  # the shape of TensorBoard's image card: not shrunk on it
    from PIL import Image

    decoded = np.asarray(Image.open(io.BytesIO(image.encoded_image_string)).convert("RGB"))
    assert decoded.shape == (image.height, image.width, 3)
    assert len(np.unique(decoded.reshape(-1, 3), axis=0)) > 50  # colour maps and text drawn, not a blank canvas
    log_dir = Path(summary["log_dir"])
    assert isinstance(yaml.safe_load((log_dir / "hparams.yaml").read_text())["shape"], list)  # plain YAML
    assert sorted(path.name for path in (log_dir / "checkpoints").iterdir()) == ["last.ckpt"]
    errors = summary["errors"]
    logged = events.Scalars("mask/rel_rms_vs_truth")[-1].value
    assert logged == pytest.approx(errors["rel_rms_vs_truth"], rel=1e-5)
    assert set(summary["localization"]) == set(held_out) == set(summary["localization_paired"])
    assert all(list(rates) == methods for rates in summary["localization"].values())  # the default score first
    assert summary["localization_levels"] == {"noise_x1": 1.0, "noise_x4": 4.0}
    assert summary["localization_calibration"] is None
    on_disk = json.loads((files["pt"].parent / "summary.json").read_text())
    assert list(on_disk["localization"]["noise_x4"]) == methods
    assert all(0 <= rate <= 1 for rates in summary["localization"].values() for rate in rates.values())
    assert Path(summary["log_dir"]).name == "lidar_0"  # named by its data


def event_values(log_dir) -> list:
    """Every summary value in the run's event files, in order."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    values = []
    for path in sorted(Path(log_dir).glob("events.out.tfevents.*")):
        values += [value for event in EventFileLoader(str(path)).Load() for value in event.summary.value]
    return values


def test_dashboards_open_on_the_answer(tmp_path):
    """The event files hold the Custom Scalars layout and the HParams session with the run's real final metrics."""
    from tensorboard.plugins.custom_scalar import layout_pb2
    from tensorboard.plugins.hparams import plugin_data_pb2

    summary = run(tmp_path)
    events = EventAccumulator(summary["log_dir"], size_guidance={"scalars": 0})
    events.Reload()
    scalars = set(events.Tags()["scalars"])
    values = event_values(summary["log_dir"])

    layouts = [value for value in values if value.tag == "custom_scalars__config__"]
    assert len(layouts) == 1
    layout = layout_pb2.Layout.FromString(layouts[0].tensor.string_val[0])
    answer, mask, every = layout.category[0], layout.category[1], layout.category[2]
    assert not answer.closed and not mask.closed and all(category.closed for category in layout.category[2:])
    assert answer.title.startswith("with the default score, does the learned mask beat a uniform variance (and ENMI)?")
    assert [chart.title.split(":")[0] for chart in answer.chart] == ["noise_x4 (x4)", "noise_x1 (x1)"]
    lines = ["ecr_learned", "ecr_true", "ecr_uniform", "ecr_best_uniform", "enmi_best_uniform"]
    for chart in answer.chart:  # one line per method: a sub-run each, so that TensorBoard gives each its colour
        (pattern,) = chart.multiline.tag
        held_out = chart.title.split(" ")[0]
        assert chart.title == f"{held_out} (x{held_out[7:]}): {', '.join(lines)}"
        for method in lines:
            sub_run = EventAccumulator(str(Path(summary["log_dir"]) / method), size_guidance={"scalars": 0})
            sub_run.Reload()
            (tag,) = [tag for tag in sub_run.Tags()["scalars"] if re.search(pattern, tag)]
            value = sub_run.Scalars(tag)[-1].value
            assert value == pytest.approx(summary["localization"][held_out][method], abs=1e-6)
    for chart in every.chart:  # every score and variance of one held-out set (TensorBoard searches the regex)
        (pattern,) = chart.multiline.tag
        matched = {tag for tag in scalars if re.search(pattern, tag)}
        held_out = chart.title.split(" ")[0]
        assert matched == {tag for tag in scalars if tag.startswith(f"localization/{held_out}/")}
        assert len(matched) == 10
    floor = mask.chart[0].multiline.tag
    assert list(floor) == ["mask/rel_rms_vs_truth", "mask/empirical_rel_rms_vs_truth"]

    hparams = [value for value in values if value.metadata.plugin_data.plugin_name == "hparams"]
    contents = [plugin_data_pb2.HParamsPluginData.FromString(value.metadata.plugin_data.content) for value in hparams]
    experiment = next(content.experiment for content in contents if content.HasField("experiment"))
    start = next(content.session_start_info for content in contents if content.HasField("session_start_info"))
    metrics = [info.name.tag for info in experiment.metric_infos]
    assert "hp_metric" not in metrics and "hp_metric" not in scalars
    assert metrics[:5] == [f"localization/noise_x4/{method}" for method in lines]  # the answer first
    assert metrics[5:10] == [f"localization/noise_x1/{method}" for method in lines]
    assert metrics[10:13] == ["mask/empirical_rel_rms_vs_truth", "mask/rel_rms_vs_empirical", "mask/rel_rms_vs_truth"]
    assert {tag for tag in scalars if tag.startswith("localization/")} <= set(metrics)
    assert {"val/nll", "speed/pairs_per_second"} <= set(metrics) <= scalars
    # HParams shows each metric's last value: the summary's numbers, not a placeholder.
    last = {tag: events.Scalars(tag)[-1].value for tag in metrics}
    assert last["mask/rel_rms_vs_truth"] == pytest.approx(summary["errors"]["rel_rms_vs_truth"], rel=1e-5)
    for held_out, rates in summary["localization"].items():
        for method, rate in rates.items():
            assert last[f"localization/{held_out}/{method}"] == pytest.approx(rate, abs=1e-6)
    assert start.hparams["data"].string_value == "lidar" and start.hparams["size"].number_value == 32
    assert start.hparams["epochs"].number_value == 2
    # The leading ones, and those the smoke config changed (TensorBoard shows five; the answer comes after them).
    assert set(start.hparams) == {"data", "epochs", "train_pairs", "size"}


class SlowEpochs(Callback):
    """0.3 s of training in each epoch's first batch, 0.5 s in each validation."""

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if batch_idx == 0:
            time.sleep(0.3)

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        time.sleep(0.5)


def test_a_run_shorter_than_the_validation_interval_validates_at_its_last_epoch(tmp_path):
    summary = run(tmp_path, "--trainer.check_val_every_n_epoch", "5")  # the smoke run has 2 epochs
    assert summary["localization"] and all(summary["localization"].values())


def test_training_speed_leaves_validation_out():
    datamodule = PairDataModule(train_pairs=32, val_pairs=8, size=16, batch_size=16)
    model = MaskFitModule(shape=datamodule.shape, localization_pairs=0)
    trainer = Trainer(
        accelerator="cpu",
        max_epochs=2,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        use_distributed_sampler=False,
        num_sanity_val_steps=0,
        check_val_every_n_epoch=1,
        enable_checkpointing=False,
        callbacks=[SlowEpochs()],
    )
    trainer.fit(model, datamodule=datamodule)
    assert len(model.epoch_seconds) == 2
    assert all(0.3 <= seconds < 0.7 for seconds in model.epoch_seconds), model.epoch_seconds  # training counted only


def test_held_out_sets_scale_the_noise_of_the_central_crop():
    model = MaskFitModule(shape=(40, 44), localization_shift=2, localization_crop=16, localization_noise=(1, 4))
    generator = torch.Generator().manual_seed(0)
    prior = 28 + torch.rand(3, 1, 40, 44, generator=generator, dtype=torch.float64) * 200  # noise x4 stays in range
    local = prior + torch.randn(3, 1, 40, 44, generator=generator, dtype=torch.float64)
    sets = model.held_out_sets(local, prior, torch.ones_like(local, dtype=torch.bool))
    assert list(sets) == ["noise_x1", "noise_x4"]
    window = (..., slice(10, 30), slice(12, 32))  # 16 + 2 x 2 around the centre of 40 x 44
    for name, factor in (("noise_x1", 1.0), ("noise_x4", 4.0)):
        set_local, set_prior, variance_factor = sets[name]
        torch.testing.assert_close(set_prior, prior[window])
        torch.testing.assert_close(set_local - set_prior, factor * (local - prior)[window])
        assert variance_factor == factor**2


@pytest.mark.parametrize(
    ("flavour", "extra"),
    [
        ("lidar", []),
        ("camera", ["--data.gain_std", "0.1", "--data.offset_std", "10", "--model.match_intensity", "true"]),
    ],
)
def test_learned_mask_matches_the_empirical_mask_and_the_truth(tmp_path, flavour, extra):
    """2,000 pairs: within 2 % of the paper's mask (ddof=1, 0.05 % above the ML optimum) and 10 % of the truth."""
    summary = run(
        tmp_path,
        *("--data.flavour", flavour, "--data.train_pairs", "2000", "--data.size", "16", "--data.batch_size", "100"),
        *("--trainer.max_epochs", "10", "--trainer.check_val_every_n_epoch", "10", *extra),
    )
    errors = summary["errors"]
    assert errors["rel_rms_vs_empirical"] < 0.02
    assert errors["rel_rms_vs_truth"] < 0.10
    # The empirical mask's own error is the sampling error sqrt(2 / n) (more with intensity matching).
    assert 0.5 * np.sqrt(2 / 2000) < errors["empirical_rel_rms_vs_truth"] < 2 * np.sqrt(2 / 2000)


def test_kept_pairs_give_the_mask_of_pairs_drawn_every_epoch(tmp_path):
    masks = []
    for keep in ("true", "false"):
        summary = run(tmp_path / keep, "--data.keep_pairs", keep, "--model.localization_pairs", "0")
        masks.append(LearnedVariance.load(summary["files"]["pt"]).variance_map())
    learned = torch.isfinite(masks[0])
    assert torch.equal(learned, torch.isfinite(masks[1])) and learned.any()
    assert torch.equal(masks[0][learned], masks[1][learned])  # bit for bit


def test_perspective_form_from_the_camera_truth(tmp_path):
    summary = run(tmp_path, "--data.flavour", "camera", "--model.form", "perspective", "--model.lr", "0.1")
    mask = LearnedVariance.load(summary["files"]["pt"])
    assert mask.form == "perspective" and summary["errors"]["rel_rms_vs_truth"] < 0.1


def test_invalid_pixels_are_never_learned(tmp_path):
    summary = run(tmp_path)
    mask = np.load(summary["files"]["npy"], allow_pickle=False)
    module = PairDataModule(train_pairs=64, val_pairs=16, size=32, batch_size=16)
    items = [module.train_set[index] for index in range(64)]
    _, defined = empirical_variance(
        torch.stack([item["local"] for item in items]),
        torch.stack([item["prior"] for item in items]),
        torch.stack([item["valid"] for item in items]),
    )
    assert np.array_equal(np.isfinite(mask), defined.numpy()) and not defined.all()


class StopAfterEpoch(Callback):
    def __init__(self, epochs: int) -> None:
        self.epochs = epochs

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        if trainer.current_epoch + 1 >= self.epochs:
            trainer.should_stop = True


def fit_directly(folder, callbacks=(), ckpt_path=None):
    datamodule = PairDataModule(train_pairs=48, val_pairs=8, size=16, batch_size=16)
    model = MaskFitModule(shape=datamodule.shape, localization_pairs=0)  # the mask alone: no held-out search
    trainer = Trainer(
        accelerator="cpu",
        max_epochs=4,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        use_distributed_sampler=False,
        num_sanity_val_steps=0,
        check_val_every_n_epoch=100,
        callbacks=[ModelCheckpoint(dirpath=folder, save_last=True), *callbacks],
    )
    trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
    return model.mask.variance_map()


def test_resume_from_checkpoint_equals_an_uninterrupted_run(tmp_path):
    uninterrupted = fit_directly(tmp_path / "straight")
    fit_directly(tmp_path / "first", [StopAfterEpoch(2)])
    resumed = fit_directly(tmp_path / "second", ckpt_path=tmp_path / "first" / "last.ckpt")
    torch.testing.assert_close(resumed, uninterrupted, equal_nan=True, rtol=1e-6, atol=0)
    halfway = torch.load(tmp_path / "first" / "last.ckpt", weights_only=True)
    assert halfway["global_step"] == 2 * 3 and bool(halfway["state_dict"]["statistics_ready"])


def test_tampered_checkpoint_is_refused(tmp_path):
    summary = run(tmp_path)
    checkpoint = torch.load(summary["last_checkpoint"], weights_only=True)
    checkpoint["callbacks"]["evil"] = Payload()
    evil = tmp_path / "evil.ckpt"
    torch.save(checkpoint, evil)
    with pytest.raises(ValueError, match="refused: it is not a plain checkpoint"):
        run(tmp_path, "--ckpt_path", str(evil))
    assert EXECUTED == []
    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes(Path(summary["last_checkpoint"]).read_bytes()[:500])
    with pytest.raises(ValueError, match="refused"):
        run(tmp_path, "--ckpt_path", str(truncated))


def test_cli_resume_continues_the_run(tmp_path):
    first = run(tmp_path)
    second = run(tmp_path, "--ckpt_path", first["last_checkpoint"], "--trainer.max_epochs", "4")
    assert second["epochs"] == 4
    checkpoint = torch.load(second["last_checkpoint"], weights_only=True)
    assert checkpoint["global_step"] == 2 * torch.load(first["last_checkpoint"], weights_only=True)["global_step"]


def test_an_earlier_runs_mask_files_are_kept_unless_overwrite(tmp_path):
    output_dir = tmp_path / "mask"
    output_dir.mkdir()
    (output_dir / "variance_mask.pt").write_bytes(b"an earlier run's mask")
    (output_dir / "summary.json").write_text("{}")
    with pytest.raises(FileExistsError, match=r"--output_dir '.*mask' already holds variance_mask\.pt, summary\.json"):
        run(tmp_path, "--output_dir", str(output_dir))
    assert (output_dir / "variance_mask.pt").read_bytes() == b"an earlier run's mask"
    summary = run(tmp_path, "--output_dir", str(output_dir), "--overwrite", "true")
    assert LearnedVariance.load(output_dir / "variance_mask.pt").shape == (32, 32)
    assert json.loads((output_dir / "summary.json").read_text()) == summary


def test_help_lists_this_commands_options_in_plain_text(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    text = capsys.readouterr().out
    assert exit_info.value.code == 0 and text.startswith("usage: enmi-fit-mask")
    assert text.index("Learn a per-pixel noise-variance mask") < text.index("--data.flavour")
    assert "(default: 2000)" in text and "examples:" in text and len(text.splitlines()) < 130
    assert ":class:" not in text and "``" not in text and "--trainer.gradient_clip_val" not in text
    with pytest.raises(SystemExit):
        main(["--help_all"])
    assert "--trainer.gradient_clip_val" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--data.flavor", "camera"], "unrecognized arguments: --data.flavor camera (did you mean --data.flavour?)"),
        (["--data.flavour", "radar"], "--data.flavour must be one of ['lidar', 'camera'], got 'radar'"),
        (["--data.root", "/nonexistent"], "--data.root must be a folder of pairs"),
        (["--data.train_pairs", "0"], "--data.train_pairs must be an int >= 1, got 0"),
        (["--model.form", "pixl"], "--model.form must be one of ['pixel', 'radial', 'perspective'], got 'pixl'"),
        (["--trainer.max_epochs", "abc"], "--trainer.max_epochs expects int or null, got 'abc'"),
        (["--ckpt_path", "missing.ckpt"], "ckpt_path must be a checkpoint file"),
        (["--ckpt-path", "missing.ckpt"], "ckpt_path must be a checkpoint file"),
    ],
)
def test_user_mistakes_end_in_one_line_and_exit_code_2(tmp_path, capsys, arguments, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["--config", SMOKE, "--trainer.logger.init_args.save_dir", str(tmp_path), *arguments])
    error_lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("enmi-fit-mask")]
    assert exit_info.value.code == 2 and len(error_lines) == 1
    assert error_lines[0].startswith("enmi-fit-mask: error: ") and message in error_lines[0]


def test_an_error_comes_alone_before_any_of_lightnings_lines(tmp_path):
    completed = subprocess.run(
        [sys.executable, str(ROOT / "train" / "fit_mask.py"), "--data.train_pairs", "0"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert completed.returncode == 2 and completed.stdout == ""
    assert completed.stderr == "enmi-fit-mask: error: --data.train_pairs must be an int >= 1, got 0\n"
    completed = subprocess.run(  # a good run prints Lightning's lines after all
        [sys.executable, str(ROOT / "train" / "fit_mask.py"), "--config", SMOKE, "--model.localization_pairs", "0"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert completed.returncode == 0 and "Seed set to 0" in completed.stderr and "GPU available" in completed.stderr


def test_debug_shows_the_exception(tmp_path):
    with pytest.raises(ValueError, match="flavour must be one of"):
        main(["--config", SMOKE, "--data.flavour", "radar", "--debug"])


def fit_in_subprocess(tmp_path, name, *overrides, output_dir=True):
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    command = [sys.executable, str(ROOT / "train" / "fit_mask.py"), "--config", SMOKE]
    command += ["--trainer.logger.init_args.save_dir", str(tmp_path / name)]
    if output_dir:
        command += ["--output_dir", str(tmp_path / name / "out")]
    subprocess.run([*command, *overrides], check=True, env=environment, cwd=tmp_path, capture_output=True, timeout=300)
    folder = tmp_path / name / "out" if output_dir else tmp_path / name / "fit_mask" / "lidar_0" / "mask"
    return np.load(folder / "variance_mask.npy", allow_pickle=False)


@pytest.mark.slow
def test_two_process_ddp_gives_the_same_mask(tmp_path):
    single = fit_in_subprocess(tmp_path, "single")
    # In the run's own folder: both processes take the one the first chose, and neither waits for the other there.
    ddp = fit_in_subprocess(tmp_path, "ddp", "--trainer.devices", "2", "--trainer.strategy", "ddp", output_dir=False)
    assert sorted(path.name for path in (tmp_path / "ddp" / "fit_mask").iterdir()) == ["lidar_0"]
    assert np.array_equal(np.isfinite(single), np.isfinite(ddp))
    np.testing.assert_allclose(ddp, single, rtol=1e-5)


def test_a_checkpoint_of_other_sizes_is_refused_naming_them(tmp_path, capsys):
    first = run(tmp_path / "small", "--data.size", "16")
    with pytest.raises(SystemExit) as exit_info:
        main(
            [
                "--config",
                SMOKE,
                "--trainer.logger.init_args.save_dir",
                str(tmp_path),
                "--ckpt_path",
                first["last_checkpoint"],
            ]
        )
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert exit_info.value.code == 2 and error.startswith("enmi-fit-mask: error: --ckpt_path")
    assert "was saved by a run of other sizes than this one of 32x32 images" in error and "(16, 16)" in error


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--torch_threads", "0"], "--torch_threads must be an int >= 1 or null, got 0"),
        (["--data.val_fraction", "1.5"], "--data.val_fraction must be in (0, 1), got 1.5"),
    ],
)
def test_zero_threads_and_a_share_above_one_end_in_one_line(tmp_path, capsys, arguments, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["--config", SMOKE, "--trainer.logger.init_args.save_dir", str(tmp_path), *arguments])
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("enmi-fit-mask")]
    assert exit_info.value.code == 2 and errors == [f"enmi-fit-mask: error: {message}"]


def test_summary_json_holds_null_where_a_value_is_not_finite_and_says_so(tmp_path, capsys, monkeypatch):
    errors = MaskFitModule.mask_errors
    monkeypatch.setattr(MaskFitModule, "mask_errors", lambda self: {**errors(self), "rel_rms_vs_empirical": math.inf})
    summary = run(tmp_path, "--output_dir", str(tmp_path / "mask"))
    text = (tmp_path / "mask" / "summary.json").read_text()
    assert "Infinity" not in text and "NaN" not in text
    assert json.loads(text)["errors"]["rel_rms_vs_empirical"] is None
    assert summary["errors"]["rel_rms_vs_empirical"] == math.inf
    assert "summary.json: errors.rel_rms_vs_empirical not finite, written as null" in capsys.readouterr().out


class CheapScores(MaskFitModule):
    """The module with NCC alone in its held-out comparison: the levels' plumbing without ECR's cost."""

    def _scores(self):
        return (NCC(),)


def fit_cheaply(folder, epochs=2, ckpt_path=None, **options):
    datamodule = PairDataModule(train_pairs=32, val_pairs=12, size=24, batch_size=4, noise_std=40.0)  # 3 batches
    model = CheapScores(shape=datamodule.shape, localization_pairs=10, localization_shift=3, **options)
    trainer = Trainer(
        accelerator="cpu",
        max_epochs=epochs,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        use_distributed_sampler=False,
        num_sanity_val_steps=0,
        check_val_every_n_epoch=1,
        callbacks=[ModelCheckpoint(dirpath=folder, save_last=True)],
    )
    trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
    return model, datamodule


def test_levels_are_read_from_the_first_held_out_pairs_and_kept_on_resume(tmp_path, monkeypatch):
    from enmi_torch.training import mask_module

    model, datamodule = fit_cheaply(tmp_path / "first")
    calibration = model.calibration
    assert calibration.pairs == 10 and model.levels == {"level_easy": calibration.easy, "level_hard": calibration.hard}
    assert set(model.held_out.rates) == {"level_easy/ncc", "level_hard/ncc"} and model.held_out.pairs == 10
    assert calibration.bracketed == "yes" and calibration.factors[0] == 1.0 and len(calibration.factors) > 2
    # The ladder's shares are those of localize on the first 10 held-out pairs, amplified and clipped, cropped as
    # the validation crops them (24 x 24 pairs: the whole image, a border of 3 pixels searched).
    items = [datamodule.val_set[index] for index in range(10)]
    local, prior, valid = (torch.stack([item[key] for item in items]) for key in ("local", "prior", "valid"))
    usable = valid & model.mask.valid_mask(local) & datamodule.truth.valid
    for factor, share in zip(calibration.factors, calibration.best, strict=True):
        searched = localization_trials(
            amplified(local, prior, factor, (0.0, 256.0)), prior, usable, {}, max_shift=3, scores=(NCC(),)
        )
        assert float(searched["ncc"].located.double().mean()) == share
    checkpoint = torch.load(tmp_path / "first" / "last.ckpt", weights_only=True)
    assert checkpoint["held_out_levels"]["levels"] == model.levels

    def refused(*args, **kwargs):
        raise AssertionError("a resumed fit reads its levels again")

    monkeypatch.setattr(mask_module, "calibrate_levels", refused)
    resumed, _ = fit_cheaply(tmp_path / "second", epochs=3, ckpt_path=tmp_path / "first" / "last.ckpt")
    assert resumed.levels == model.levels and resumed.calibration == calibration
    by_hand, _ = fit_cheaply(tmp_path / "third", epochs=1, localization_noise=(1.0, 3.0))  # no ladder either
    assert by_hand.levels == {"noise_x1": 1.0, "noise_x3": 3.0} and by_hand.calibration is None
