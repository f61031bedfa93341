"""A fit stopped part-way (SIGKILL, SIGTERM, SIGINT) keeps a checkpoint and resumes to an uninterrupted run's mask."""

import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from lightning.pytorch import Callback, Trainer
from lightning.pytorch.callbacks import ModelCheckpoint
from torch.utils._pytree import tree_leaves

from enmi_torch.data import PairDataModule
from enmi_torch.data.resumable import ResumableLoader, ResumableSampler
from enmi_torch.training.fit_mask import fit_mask
from enmi_torch.training.mask_module import MaskFitModule
from enmi_torch.training.preemption import Preemption, _without_ckpt_path

ROOT = Path(__file__).resolve().parents[2]
SMOKE = str(ROOT / "configs" / "fit_mask_smoke.yaml")
# 4 steps per epoch, about 0.05 s each: long enough to stop part-way, no validation until the end.
LONGER = ["--trainer.max_epochs", "200", "--trainer.check_val_every_n_epoch", "1000", "--model.localization_pairs", "0"]


@pytest.fixture(autouse=True)
def _threads(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["fit_mask.py"])
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def arguments(tmp_path, name):
    save_dir, output_dir = tmp_path / name, tmp_path / name / "out"
    return [
        "--config",
        SMOKE,
        *LONGER,
        "--trainer.logger.init_args.save_dir",
        str(save_dir),
        "--output_dir",
        str(output_dir),
    ]


def start(tmp_path, name):
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}
    command = [sys.executable, str(ROOT / "train" / "fit_mask.py"), *arguments(tmp_path, name)]
    process = subprocess.Popen(command, cwd=tmp_path, env=environment, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    return process, tmp_path / name / "fit_mask" / "lidar_0" / "checkpoints" / "last.ckpt"


def wait_for_epochs(process, checkpoint, epochs, timeout=120.0):
    """Wait until ``checkpoint`` holds ``epochs`` finished epochs (the run still going)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert process.poll() is None, process.communicate()
        if checkpoint.is_file():
            try:
                if torch.load(checkpoint, weights_only=True)["epoch"] >= epochs - 1:
                    return
            except (RuntimeError, EOFError, KeyError):  # being written
                pass
        time.sleep(0.05)
    process.kill()
    raise AssertionError(f"no checkpoint of {epochs} epochs in {timeout} s")


def mask(summary):
    return np.load(summary["files"]["npy"], allow_pickle=False)


@pytest.mark.slow
def test_a_run_killed_part_way_resumes_to_the_mask_of_an_uninterrupted_run(tmp_path):
    process, checkpoint = start(tmp_path, "killed")
    wait_for_epochs(process, checkpoint, 3)
    process.send_signal(signal.SIGKILL)
    process.communicate(timeout=60)
    assert process.returncode == -signal.SIGKILL
    halfway = torch.load(checkpoint, weights_only=True)
    assert 3 <= halfway["epoch"] + 1 < 200 and halfway["global_step"] == 4 * (halfway["epoch"] + 1)  # an epoch's end

    resumed = fit_mask([*arguments(tmp_path, "resumed"), "--ckpt_path", str(checkpoint)])
    uninterrupted = fit_mask(arguments(tmp_path, "uninterrupted"))
    assert resumed["epochs"] == uninterrupted["epochs"] == 200
    np.testing.assert_allclose(mask(resumed), mask(uninterrupted), rtol=1e-6, atol=0)
    final = torch.load(resumed["last_checkpoint"], weights_only=True)
    assert final["global_step"] == torch.load(uninterrupted["last_checkpoint"], weights_only=True)["global_step"]


@pytest.mark.slow
@pytest.mark.parametrize("stop, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_sigterm_and_sigint_write_a_checkpoint_and_say_how_to_resume(tmp_path, stop, code):
    process, checkpoint = start(tmp_path, "stopped")
    wait_for_epochs(process, checkpoint, 2)
    process.send_signal(stop)
    _, stderr = process.communicate(timeout=60)
    stderr = stderr.decode()
    assert process.returncode == code, stderr
    lines = [line for line in stderr.splitlines() if line.startswith("enmi-fit-mask: stopped")]
    assert len(lines) == 1, stderr
    name = signal.Signals(stop).name
    found = re.fullmatch(
        rf"enmi-fit-mask: stopped by {name} at epoch (\d+), step (\d+); checkpoint (.+); resume with: (.+)", lines[0]
    )
    assert found, lines[0]
    assert Path(found.group(3)) == checkpoint and not (tmp_path / "stopped" / "out").exists()  # no mask, a checkpoint
    saved = torch.load(checkpoint, weights_only=True)
    assert saved["global_step"] == int(found.group(2)) and saved["epoch"] == int(found.group(1))
    hint = shlex.split(found.group(4))
    assert hint[0] == "enmi-fit-mask" and hint[-2:] == ["--ckpt_path", str(checkpoint)]
    assert hint[1:-2] == arguments(tmp_path, "stopped")
    if stop == signal.SIGTERM:  # the hint's command finishes the run, to the uninterrupted run's mask
        resumed = fit_mask(hint[1:])
        assert resumed["epochs"] == 200 and np.isfinite(mask(resumed)).any()
        final = torch.load(resumed["last_checkpoint"], weights_only=True)
        assert final["global_step"] == 4 * 200
        uninterrupted = fit_mask(arguments(tmp_path, "uninterrupted"))
        np.testing.assert_allclose(mask(resumed), mask(uninterrupted), rtol=1e-6, atol=0)


def _quiet_trainer(folder, max_epochs, *callbacks):
    """A CPU trainer without logger, progress bar or validation, writing under ``folder``."""
    return Trainer(
        accelerator="cpu",
        max_epochs=max_epochs,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        use_distributed_sampler=False,
        num_sanity_val_steps=0,
        check_val_every_n_epoch=100,
        default_root_dir=folder,
        callbacks=list(callbacks),
    )


def test_the_resume_hint_replaces_an_earlier_ckpt_path():
    command = ["enmi-fit-mask", "--ckpt_path", "a.ckpt", "--data.size", "32", "--ckpt-path=b.ckpt"]
    assert _without_ckpt_path(command) == ["enmi-fit-mask", "--data.size", "32"]
    with pytest.raises(ValueError, match="every_n_train_steps must be an int >= 1 or null, got 0"):
        Preemption(every_n_train_steps=0)


def test_a_checkpoint_every_n_training_steps_within_an_epoch(tmp_path):
    saved = []

    class Watched(Preemption):
        def save(self, trainer):
            path = super().save(trainer)
            saved.append((trainer.global_step, torch.load(path, weights_only=True)["global_step"]))
            return path

    datamodule = PairDataModule(train_pairs=48, val_pairs=8, size=16, batch_size=16)  # 3 steps per epoch
    trainer = _quiet_trainer(
        tmp_path, 2, ModelCheckpoint(dirpath=tmp_path, save_last=True), Watched(every_n_train_steps=2)
    )
    trainer.fit(MaskFitModule(shape=datamodule.shape), datamodule=datamodule, weights_only=True)
    assert saved == [(2, 2), (3, 3), (4, 4), (6, 6)]  # steps 2 and 4, the ends of epochs (3, 6), not twice at 6
    assert not list(tmp_path.glob(".*partial"))


class _Seen(Callback):
    """The sum of each training batch's first tensor, in the order the fit sees them; SIGTERM noted at ``stop_at``."""

    def __init__(self, preemption: Preemption | None = None, stop_at: int | None = None) -> None:
        self.sums, self.preemption, self.stop_at = [], preemption, stop_at

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.sums.append(float(tree_leaves(batch)[0].double().sum()))

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == self.stop_at:  # as if the scheduler sent SIGTERM during this step
            self.preemption._signal = signal.SIGTERM


def test_a_fit_stopped_mid_epoch_resumes_on_the_next_batch_to_the_uninterrupted_weights(tmp_path):
    def fit(folder, callbacks, ckpt_path=None):
        datamodule = PairDataModule(train_pairs=48, val_pairs=8, size=16, batch_size=16, seed=3)  # 3 steps per epoch
        module = MaskFitModule(shape=datamodule.shape)
        folder = tmp_path / folder
        trainer = _quiet_trainer(folder, 3, ModelCheckpoint(dirpath=folder, save_top_k=0, save_last=True), *callbacks)
        trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=ckpt_path is None)
        return module

    torch.manual_seed(0)
    whole = _Seen()
    uninterrupted = fit("whole", [whole])
    assert len(whole.sums) == 9 and len(set(whole.sums)) == 9

    torch.manual_seed(0)
    preemption = Preemption()
    stopped = _Seen(preemption, stop_at=5)  # the 2nd of epoch 1's 3 steps
    with pytest.raises(SystemExit) as stop:
        fit("stopped", [stopped, preemption])
    assert stop.value.code == 143 and stopped.sums == whole.sums[:5]
    checkpoint = tmp_path / "stopped" / "last.ckpt"
    state = torch.load(checkpoint, weights_only=False)
    assert state["global_step"] == 5 and state["loops"]["fit_loop"]["state_dict"]["combined_loader"] == [
        {"epoch": 1, "batches": 2}
    ]

    rest = _Seen()
    resumed = fit("resumed", [rest], ckpt_path=checkpoint)
    assert stopped.sums + rest.sums == whole.sums  # the last batch of epoch 1, then epoch 2: no batch twice
    for (name, value), (_, expected) in zip(
        resumed.state_dict().items(), uninterrupted.state_dict().items(), strict=True
    ):
        torch.testing.assert_close(value, expected, rtol=0, atol=0, msg=name)


def test_a_resumable_loader_skips_only_within_the_epoch_it_stopped_in():
    dataset = torch.arange(10.0)
    loader = ResumableLoader(dataset, batch_size=4, sampler=ResumableSampler(dataset, 1, 0, shuffle=False))
    assert [batch.tolist() for batch in loader] == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9]]
    assert loader.state_dict() == {"epoch": 0, "batches": 3}
    loader.load_state_dict({"epoch": 0, "batches": 1})
    assert [batch.tolist() for batch in loader] == [[4, 5, 6, 7], [8, 9]] and loader.state_dict()["batches"] == 3
    loader.load_state_dict({"epoch": 0, "batches": 3})  # the epoch's end: the next pass is whole
    assert len(list(loader)) == 3
    loader.load_state_dict({"epoch": 4, "batches": 1})  # another epoch's state
    assert len(list(loader)) == 3
    with pytest.raises(ValueError, match="a ResumableLoader state must be"):
        loader.load_state_dict({"batches": 1})
    with pytest.raises(TypeError, match="sampler must be a ResumableSampler, got SequentialSampler"):
        ResumableLoader(dataset, batch_size=4)


class _LightningsOwnStop(Callback):
    """Notes SIGTERM as Lightning's handler does, after the preemption callback looked at this step: Lightning then
    stops the fit itself (``SIGTERMException``), and the callback hears of it only through ``on_exception``."""

    def __init__(self, at_step: int) -> None:
        self.at_step = at_step

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == self.at_step:
            trainer._signal_connector.received_sigterm = True


def test_lightnings_own_sigterm_stop_after_an_earlier_checkpoint_writes_the_current_step(tmp_path, capsys):
    """A checkpoint at epoch 0's end (step 3), then Lightning's SIGTERM stop at step 5: last.ckpt must hold step 5, so
    that the steps since the epoch's checkpoint are not lost (the mutation survivor of issue 43)."""
    datamodule = PairDataModule(train_pairs=48, val_pairs=8, size=16, batch_size=16, seed=3)  # 3 steps per epoch
    preemption = Preemption()
    preemption.command = ["enmi-fit-mask", "--data.size", "16"]
    trainer = _quiet_trainer(
        tmp_path, 3, ModelCheckpoint(dirpath=tmp_path, save_top_k=0, save_last=True), preemption, _LightningsOwnStop(5)
    )
    with pytest.raises(SystemExit) as stop:
        trainer.fit(MaskFitModule(shape=datamodule.shape), datamodule=datamodule, weights_only=True)
    assert type(stop.value).__name__ == "SIGTERMException"  # Lightning's own stop, not the callback's
    state = torch.load(tmp_path / "last.ckpt", weights_only=False)
    assert state["global_step"] == 5 and state["epoch"] == 1
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line == (
        f"enmi-fit-mask: stopped by SIGTERM at epoch 1, step 5; checkpoint {tmp_path / 'last.ckpt'}; resume with: "
        f"enmi-fit-mask --data.size 16 --ckpt_path {tmp_path / 'last.ckpt'}"
    )


def test_without_a_checkpoint_callback_the_checkpoint_goes_to_the_run_folders_checkpoints(tmp_path):
    datamodule = PairDataModule(train_pairs=32, val_pairs=8, size=16, batch_size=16)
    trainer = Trainer(
        accelerator="cpu",
        max_epochs=1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        use_distributed_sampler=False,
        num_sanity_val_steps=0,
        check_val_every_n_epoch=100,
        default_root_dir=tmp_path,
        callbacks=[Preemption()],
    )
    trainer.fit(MaskFitModule(shape=datamodule.shape), datamodule=datamodule, weights_only=True)
    assert torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 2
