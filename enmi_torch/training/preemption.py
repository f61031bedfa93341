"""A fit that survives being stopped: checkpoints during training, SIGTERM and SIGINT handled as a preemption.

:class:`Preemption` writes ``last.ckpt`` (where :class:`~lightning.pytorch.callbacks.ModelCheckpoint` puts it; with
``save_top_k=0`` that one writes it only at the end of the run) at the end of every epoch, every
``every_n_train_steps`` steps within an epoch, and when the process gets
SIGTERM (what a cluster scheduler sends before preempting a job) or SIGINT (Ctrl+C) it finishes the current step,
writes ``last.ckpt``, prints one line saying how to resume and ends the run with :class:`Preempted` (exit code 143
for SIGTERM, 130 for SIGINT). A second Ctrl+C stops at once, without a checkpoint.

Resuming gives the mask of an uninterrupted run, from an epoch's end or from within an epoch: the training loader
(:class:`~enmi_torch.data.resumable.ResumableLoader`) goes on from the batch after the checkpoint's.
"""

from __future__ import annotations

import os
import shlex
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from lightning.pytorch import Callback
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities.exceptions import SIGTERMException

# Exit codes of a run stopped by a signal: 128 + the signal's number, as a shell reports a process it killed.
EXIT_CODES = {signal.SIGTERM: 128 + signal.SIGTERM, signal.SIGINT: 128 + signal.SIGINT}


class Preempted(SystemExit):
    """The run was stopped by a signal after writing its checkpoint; ``code`` is 143 (SIGTERM) or 130 (SIGINT)."""


class Preemption(Callback):
    """``last.ckpt`` every epoch, every ``every_n_train_steps`` steps (``None``: epochs only) and on SIGTERM/SIGINT.

    ``command``: the command line that started the run (the resume hint repeats it with ``--ckpt_path``); the
    fit-mask command sets it.
    """

    def __init__(self, every_n_train_steps: int | None = None) -> None:
        if every_n_train_steps is not None and (isinstance(every_n_train_steps, bool) or every_n_train_steps < 1):
            raise ValueError(f"every_n_train_steps must be an int >= 1 or null, got {every_n_train_steps!r}")
        self.every_n_train_steps = every_n_train_steps
        self.command: Sequence[str] = ("enmi-fit-mask",)
        self._signal: int | None = None
        self._previous_sigint = None
        self._saved: tuple[int, int, Path] | None = None  # epoch, step and path of the last checkpoint written

    # Signals -------------------------------------------------------------------------------------------------------

    def on_train_start(self, trainer, pl_module) -> None:
        """Turn SIGINT into a request to stop after the current step (Lightning already notes SIGTERM so)."""
        self._signal, self._saved = None, None
        try:
            self._previous_sigint = signal.signal(signal.SIGINT, self._on_sigint)
        except ValueError:  # not the main thread: Ctrl+C stays Lightning's
            self._previous_sigint = None

    def _on_sigint(self, signum, frame) -> None:
        if self._signal == signal.SIGINT:  # the second Ctrl+C: stop now
            raise KeyboardInterrupt
        self._signal = signal.SIGINT

    def _restore_sigint(self) -> None:
        if self._previous_sigint is not None:
            signal.signal(signal.SIGINT, self._previous_sigint)
            self._previous_sigint = None

    def on_train_end(self, trainer, pl_module) -> None:
        """Give Ctrl+C back to Python's handler."""
        self._restore_sigint()

    def on_exception(self, trainer, pl_module, exception: BaseException) -> None:
        """Lightning's own SIGTERM stop (between steps, at an epoch's end, in validation): a checkpoint and the hint."""
        self._restore_sigint()
        if isinstance(exception, SIGTERMException) and not isinstance(exception, Preempted):
            if trainer.training and (self._saved is None or self._saved[1] != trainer.global_step):
                self.save(trainer)  # between two training steps; in validation, the last checkpoint stands
            self._report(trainer, signal.SIGTERM)

    def _report(self, trainer, stop: int) -> None:
        """One line on stderr: which signal, the checkpoint and its epoch and step, the command that resumes."""
        if not trainer.is_global_zero:
            return
        name = signal.Signals(stop).name
        if self._saved is None:
            line = f"stopped by {name} before a checkpoint; start again with: {shlex.join(self.command)}"
        else:
            epoch, step, path = self._saved
            resume = shlex.join([*_without_ckpt_path(self.command), "--ckpt_path", str(path)])
            line = f"stopped by {name} at epoch {epoch}, step {step}; checkpoint {path}; resume with: {resume}"
        sys.stderr.write(f"{self.command[0]}: {line}\n")
        sys.stderr.flush()

    def _stop_signal(self, trainer) -> int | None:
        if trainer.received_sigterm:
            return signal.SIGTERM
        return self._signal

    # Checkpoints ---------------------------------------------------------------------------------------------------

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx: int) -> None:
        """A checkpoint every ``every_n_train_steps`` steps within an epoch; on a signal, a checkpoint and the end."""
        stop = self._stop_signal(trainer)
        if stop is not None:
            self.save(trainer)
            self._restore_sigint()
            self._report(trainer, stop)
            raise Preempted(EXIT_CODES[stop])
        last_of_epoch = batch_idx + 1 >= trainer.num_training_batches  # the epoch's own checkpoint follows
        if self.every_n_train_steps and trainer.global_step % self.every_n_train_steps == 0 and not last_of_epoch:
            self.save(trainer)

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        """``last.ckpt`` at the end of every epoch (resuming from it gives the uninterrupted run's mask)."""
        self.save(trainer)

    def save(self, trainer) -> Path:
        """Write ``last.ckpt`` whole or not at all (a kill while writing keeps the earlier one); returns its path."""
        checkpoint = trainer.checkpoint_callback
        if isinstance(checkpoint, ModelCheckpoint) and checkpoint.dirpath is not None:
            folder = Path(checkpoint.dirpath)
            name = checkpoint.CHECKPOINT_NAME_LAST + checkpoint.FILE_EXTENSION
        else:
            folder, name = Path(trainer.log_dir or trainer.default_root_dir) / "checkpoints", "last.ckpt"
        path = folder / name
        partial = folder / f".{name}.partial"
        trainer.save_checkpoint(partial, weights_only=False)  # the whole state: optimizer, schedule, loops
        if trainer.is_global_zero:
            os.replace(partial, path)
        trainer.strategy.barrier("preemption_checkpoint")
        if isinstance(checkpoint, ModelCheckpoint):
            checkpoint.last_model_path = str(path)
        self._saved = (trainer.current_epoch, trainer.global_step, path)
        return path


def _without_ckpt_path(command: Sequence[str]) -> list[str]:
    """``command`` less an earlier ``--ckpt_path X`` / ``--ckpt_path=X`` (the hint adds the new one)."""
    kept, skip = [], False
    for argument in command:
        if skip:
            skip = False
        elif argument in ("--ckpt_path", "--ckpt-path"):
            skip = True
        elif not argument.startswith(("--ckpt_path=", "--ckpt-path=")):
            kept.append(argument)
    return kept
