"""``MaskFitModule``: fits a :class:`~enmi_torch.variance.LearnedVariance` to local/prior pairs with Lightning.

Before the first step one pass over the training pairs (each seen once over all processes, sums all-reduced) gives
the paper's empirical mask, the pixels that can be learned (observed valid at least twice) and a constant start.
Training minimises the Gaussian NLL of the residuals ``local - prior`` per pixel, averaged over pairs, plus the
mask's smoothness prior divided by the number of training pairs. Each step's loss is normalised by a constant (the
pairs in the process's batch times the pixels per image), so the gradient averaged by DDP over processes equals the
single-process gradient of the same global batch: the fitted mask does not depend on the number of processes.

Dashboards (TensorBoard, written by :class:`~enmi_torch.training.logger.MaskLogger`): ``train/nll`` and ``val/nll``
(the one loss, per valid pixel); ``mask/rel_rms_vs_empirical``, ``mask/rel_rms_vs_truth`` and its floor
``mask/empirical_rel_rms_vs_truth``; ``localization/<held-out set>/<method>`` (share of held-out pairs located
within one pixel by :func:`~enmi_torch.localize`, the localization yardstick's protocol) and
``localization_z/<held-out set>/<method>`` (the mean z-score of the true shift's score among the others: the margin)
for the methods of :data:`~enmi_torch.training.held_out.METHOD_MEANINGS`: the library's default score ``ECR()``
first, then ENMI (the paper's), each with the learned mask (``*_learned``), the true field (``*_true``, where the
pairs name one), one uniform variance (``*_uniform``: the learned mask's mean) and the best of the mean times
``localization_grid`` (``*_best_uniform``, an oracle), then hard NMI and NCC. The held-out sets are the validation
pairs with their residuals ``local - prior`` amplified (the variance by the factor squared; every variance map
scaled alike) and clipped to ``value_range``: at levels read from those pairs at the fit's start
(:func:`~enmi_torch.training.held_out.calibrate_levels`: ``level_hard``, where the best method finds half the pairs,
and ``level_easy``, a quarter of it), or at the factors of ``localization_noise`` (``noise_x16``). The methods that
do not depend on the mask are scored at a fit's first validation and reused (the same pairs give the same scores).
``speed/pairs_per_second`` (training only, validation left out); the mask figure; histograms of raw and
standardised residuals.
"""

from __future__ import annotations

import inspect
import math
import sys
import time
from typing import NamedTuple

import numpy as np
import torch
from lightning.pytorch import LightningModule
from torch import Tensor

from enmi_torch.data import match_intensity
from enmi_torch.data.truth import FLAVOURS
from enmi_torch.scores import ECR, ENMI, NCC, NMI, Score
from enmi_torch.training.fit_checks import check_model_options
from enmi_torch.training.held_out import (
    ANSWER_METHODS,
    CALIBRATION_PAIRS,
    HeldOutSummary,
    HeldOutTally,
    LevelCalibration,
    amplified,
    calibrate_levels,
    held_out_order,
    localization_trials,
    trial_methods,
)
from enmi_torch.training.localization_figure import localization_figure
from enmi_torch.training.logger import MaskLogger
from enmi_torch.training.mask_figure import mask_figure, masked_residual
from enmi_torch.utils.checks import check_option
from enmi_torch.utils.files import read_npy
from enmi_torch.utils.options import OptionError, signature_defaults
from enmi_torch.variance import EmpiricalVariance, LearnedVariance
from enmi_torch.variance.learned import FORMS


def relative_rms(estimate: Tensor, reference: Tensor, valid: Tensor) -> float:
    """``sqrt(mean((estimate / reference - 1)^2))`` over ``valid`` pixels of two ``(H, W)`` maps."""
    ratio = estimate[valid].double() / reference[valid].double()
    return float((ratio - 1).square().mean().sqrt())


class HeldOutView(NamedTuple):
    """Held-out pairs' searched window (:meth:`MaskFitModule._held_out_view`), the variances cropped alike."""

    local: Tensor
    prior: Tensor
    usable: Tensor  # bool: valid, learned and (where the pairs name a truth) in its field
    learned: Tensor  # the learned mask
    truth: Tensor | None  # the true variance, where the pairs name one
    uniform: float  # the learned mask's mean


class MaskFitModule(LightningModule):
    """Learns a variance mask from the pairs of a :class:`~enmi_torch.data.PairDataModule`.

    Args:
        shape: ``(H, W)`` of the images (``fit_mask.py`` links it to the data's).
        form: ``"pixel"``, ``"radial"`` or ``"perspective"`` (see :class:`~enmi_torch.variance.LearnedVariance`).
        smoothness: precision of the smoothness prior, in units of the summed log-likelihood of all pairs.
        degree: polynomial degree of the ``"radial"`` form.
        analytic_variance: ``.npy`` analytic variance map for the ``"perspective"`` form; ``None`` takes the data's
            known field (synthetic camera-like pairs).
        match_intensity: fit a gain and offset per pair before taking residuals (for intensity changes).
        lr: Adam learning rate, annealed to 0 by a cosine over the run.
        localization_pairs: held-out pairs searched per validation (the first ones; 0 turns the search off).
        localization_shift: the shifts searched are ``[-s, s]^2`` pixels.
        localization_crop: side of the central square searched in each held-out pair (smaller: harder).
        localization_noise: ``None`` (null, the default) reads the held-out levels from the held-out pairs at the
            fit's first validation: ``level_hard``, where the best method finds half the pairs, and ``level_easy``, a
            quarter of its factor (:func:`~enmi_torch.training.held_out.calibrate_levels`); factors (``[1, 16, 32]``)
            give them by hand, one held-out set each (``noise_x<k>``; 1: the pairs as they are).
        localization_grid: factors of the uniform variance tried by the best-uniform controls (with 1).
        bins: ECR/ENMI/NMI bins for the localization score.
        value_range: bin range.
    """

    def __init__(
        self,
        shape: tuple[int, int] = (128, 128),
        form: str = "pixel",
        smoothness: float = 0.0,
        degree: int = 4,
        analytic_variance: str | None = None,
        match_intensity: bool = False,
        lr: float = 0.05,
        localization_pairs: int = 64,
        localization_shift: int = 4,
        localization_crop: int = 32,
        localization_noise: tuple[float, ...] | None = None,
        localization_grid: tuple[float, ...] = (0.25, 4.0),
        bins: int = 32,
        value_range: tuple[float, float] = (0.0, 256.0),
    ) -> None:
        options = {name: value for name, value in locals().items() if name not in ("self", "__class__")}
        super().__init__()
        check_option("form", form, FORMS)  # here, not when the mask is built at the fit's start
        check_model_options(options, signature_defaults(MaskFitModule.__init__))  # every option, before any work
        # Lists, not tuples: hparams.yaml stays plain YAML (no !!python/tuple tags).
        shape, value_range = [int(size) for size in shape], [float(value) for value in value_range]
        if localization_noise is not None:
            localization_noise = [float(factor) for factor in localization_noise]
        localization_grid = [float(factor) for factor in localization_grid]
        self.save_hyperparameters()
        self.shape = (shape[0], shape[1])
        self.mask: LearnedVariance | None = None
        self.statistics = EmpiricalVariance(self.shape)
        self.register_buffer("statistics_ready", torch.tensor(False))
        self._tally: HeldOutTally | None = None
        self._trials = 0
        self.held_out: HeldOutSummary | None = None  # the last validation's comparison
        # The held-out sets' factors by name, and how they were read (None: given by hand).
        self.levels: dict[str, float] | None = None
        if localization_noise is not None:
            self.levels = {f"noise_x{factor:g}": factor for factor in localization_noise}
        self.calibration: LevelCalibration | None = None
        self._histogram_batch: tuple[Tensor, Tensor] | None = None
        self._clock, self._train_seconds, self._epoch_pairs = 0.0, 0.0, 0
        self.epoch_seconds: list[float] = []
        self._figure_pair: tuple[Tensor, Tensor, Tensor] | None = None
        self._fixed_results: dict[tuple, dict] = {}

    # ----- set-up -------------------------------------------------------------------------------------------------
    @property
    def truth(self):
        """The data's known noise field, or ``None``."""
        datamodule = self.trainer.datamodule if self._trainer is not None else None
        return getattr(datamodule, "truth", None)

    def configure_model(self) -> None:
        """Build the mask (its analytic map may come from the data)."""
        if self.mask is None:
            self.mask = self.build_mask(self.truth)

    def build_mask(self, truth) -> LearnedVariance:
        """The mask these options make, ``truth`` the data's known field or ``None``.

        The command builds one before training, so that a mistake in the mask's options stops it before it starts.
        """
        hparams = self.hparams
        analytic = valid = None
        if hparams.form == "perspective":
            analytic = self._analytic_variance(truth)
            valid = torch.isfinite(analytic) & (analytic > 0)
        return LearnedVariance(
            self.shape,
            hparams.form,
            degree=hparams.degree,
            analytic_variance=analytic,
            valid=valid,
            smoothness=hparams.smoothness,
        )

    def _analytic_variance(self, truth) -> Tensor:
        path = self.hparams.analytic_variance
        if path is not None:
            analytic = torch.from_numpy(read_npy(path, "analytic_variance").astype(np.float64))
        elif truth is not None:
            analytic = truth.variance
        else:
            raise OptionError(
                lambda spell: (
                    f"{spell('form', 'perspective')} needs an analytic variance map when the data has no "
                    f"known field: pass {spell('analytic_variance', 'MAP.npy')}"
                )
            )
        if tuple(analytic.shape) != self.shape:
            raise ValueError(f"analytic_variance must be an {self.shape} map, got shape {tuple(analytic.shape)}")
        return analytic

    def configure_optimizers(self):
        """Adam on the mask, learning rate annealed to 0 by a cosine over the run's steps."""
        optimizer = torch.optim.Adam(self.mask.parameters(), lr=self.hparams.lr)
        total = max(1, int(self.trainer.estimated_stepping_batches))

        def cosine(step: int) -> float:
            return 0.5 * (1 + math.cos(math.pi * min(step / total, 1.0)))

        # A function (not a stored object): a resumed run anneals over its own length, from the restored step.
        schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, cosine)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": schedule, "interval": "step"}}

    def on_fit_start(self) -> None:
        """One pass over the training pairs: empirical mask, learnable pixels, starting variance."""
        if not bool(self.statistics_ready):
            self.statistics.reset()
            with torch.no_grad():
                for batch in self.trainer.datamodule.statistics_dataloader():
                    local, prior, valid = self._pair(batch)
                    self.statistics.update(local, prior, valid)
            self.statistics.all_reduce()
            _, observed = self.statistics.compute()
            learnable = observed & self.mask.valid
            if not bool(learnable.any()):
                raise ValueError("no pixel is valid in two training pairs or more: nothing to learn a variance from")
            self.mask.set_valid(learnable)
            sum_squares, count = self.statistics.sum_squares[learnable].sum(), self.statistics.count[learnable].sum()
            self.mask.reset_parameters(max(float(sum_squares / count), 1e-12))
            self.statistics_ready.fill_(True)

    def read_levels(self) -> LevelCalibration:
        """Read the held-out levels from the first held-out pairs (:func:`~.held_out.calibrate_levels`).

        Called at the fit's first validation. ECR and ENMI with the true map (where the pairs name one) and with one
        uniform variance (the mask's mean then), NMI and NCC search the first :data:`~.held_out.CALIBRATION_PAIRS`
        pairs of the held-out set at each factor of the ladder; every process reads the same pairs, so all get the
        same levels. Sets :attr:`levels` (``level_easy``, ``level_hard``) and :attr:`calibration`, and returns the
        latter (``None`` without held-out pairs to search).
        """
        val_set = self.trainer.datamodule.val_set
        count = min(self.hparams.localization_pairs, CALIBRATION_PAIRS, len(val_set))
        if count == 0:
            self.levels = {}
            return None
        items = [val_set[index] for index in range(count)]
        batch = {key: torch.stack([item[key] for item in items]) for key in ("local", "prior", "valid")}
        shift, value_range = self.hparams.localization_shift, tuple(self.hparams.value_range)
        bar = self.trainer.progress_bar_callback if self.trainer.is_global_zero else None

        def show(text: str) -> None:  # on the progress bar's stream, between its lines
            if bar is not None:
                bar.print(text, file=sys.stderr)

        start = time.perf_counter()
        with torch.no_grad():
            local, prior, valid = self._pair(batch)
            view = self._held_out_view(local, prior, valid)

            def rates_at(factor: float) -> dict[str, float]:
                variances = {"uniform": view.uniform * factor**2}
                if view.truth is not None:
                    variances["true"] = view.truth * factor**2
                set_local = amplified(view.local, view.prior, factor, value_range)
                results = localization_trials(
                    set_local, view.prior, view.usable, variances, max_shift=shift, scores=self._scores()
                )
                rates = {method: float(trial.located.double().mean()) for method, trial in results.items()}
                show(f"held-out level x{factor:g}: best share {max(rates.values()):.2f}")
                return rates

            self.calibration = calibrate_levels(rates_at, count)
        self.levels = self.calibration.levels()
        show(
            f"held-out levels: level_hard x{self.calibration.hard:g}, level_easy x{self.calibration.easy:g} "
            f"({time.perf_counter() - start:.0f} s)"
        )
        return self.calibration

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """The held-out levels read at the fit's start: a resumed fit searches the same sets."""
        calibration = None if self.calibration is None else self.calibration._asdict()
        checkpoint["held_out_levels"] = {"levels": self.levels, "calibration": calibration}

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Restore the held-out levels of :meth:`on_save_checkpoint` (given by hand: this run's options rule)."""
        saved = checkpoint.get("held_out_levels")
        if saved is None or self.hparams.localization_noise is not None:
            return
        self.levels = saved["levels"]
        self.calibration = None if saved["calibration"] is None else LevelCalibration(**saved["calibration"])

    def on_fit_end(self) -> None:
        """Hand the final metrics to HParams; forget the localization results kept between validations."""
        self._fixed_results = {}
        if isinstance(self.logger, MaskLogger):
            final = ("localization/", "mask/", "val/nll", "speed/")
            metrics = [key for key in self.trainer.callback_metrics if key.startswith(final)]
            held_out = held_out_order({key.split("/")[1] for key in metrics if key.startswith("localization/")})[::-1]
            rank = {name: index for index, name in enumerate(held_out)}  # the hardest set first

            def order(key: str) -> tuple:  # the answer's lines first, then the mask's errors, then the rest
                parts = key.split("/")
                if parts[0] == "localization" and parts[2] in ANSWER_METHODS:
                    return 0, rank[parts[1]], ANSWER_METHODS.index(parts[2]), key
                return 1 if parts[0] == "mask" else 2, rank.get(parts[1], len(rank)), 0, key

            metrics.sort(key=order)
            datamodule = self.trainer.datamodule
            data = datamodule.hparams if datamodule is not None else {}
            source = data.get("root") or data.get("flavour", "")
            defaults = {}
            for owner in (self, datamodule):
                if owner is not None:
                    parameters = inspect.signature(type(owner).__init__).parameters.values()
                    defaults.update({item.name: item.default for item in parameters if item.default is not item.empty})
            self.logger.log_final_metrics(metrics, {"data": str(source), "epochs": self.current_epoch}, defaults)

    def on_train_start(self) -> None:
        """Lay out the Custom Scalars tab, once the held-out levels are known (else at the first validation)."""
        if self.levels is not None:
            self._log_layout()

    def _log_layout(self) -> None:
        """The Custom Scalars tab: the held-out sets, hardest first, each with its factor, and the mask's errors."""
        if isinstance(self.logger, MaskLogger):
            levels = self.levels or {}
            sets = {name: f"{name} (x{levels[name]:g})" for name in held_out_order(levels)[::-1]}
            self.logger.log_layout(sets, self.truth is not None)

    def _pair(self, batch: dict) -> tuple[Tensor, Tensor, Tensor]:
        local, prior, valid = batch["local"].to(self.device), batch["prior"].to(self.device), batch["valid"]
        valid = valid.to(self.device)
        if self.hparams.match_intensity:
            prior = match_intensity(local, prior, valid)
        return local, prior, valid

    # ----- steps --------------------------------------------------------------------------------------------------
    def _step(self, batch: dict, stage: str) -> Tensor:
        local, prior, valid = self._pair(batch)
        terms = self.mask.nll(local, prior, valid, reduction="none")
        batch_size, pixels = local.shape[0], self.shape[0] * self.shape[1]
        valid_pixels = (valid & self.mask.valid_mask(local)).sum().clamp_min(1)
        self.log(
            f"{stage}/nll",
            terms.sum() / valid_pixels,
            on_epoch=True,
            on_step=False,
            sync_dist=True,
            batch_size=batch_size,
            prog_bar=stage == "val",
        )
        loss = terms.sum() / (batch_size * pixels)
        if stage == "train":
            pairs = self.trainer.datamodule.num_train_pairs
            loss = loss + self.mask.penalty() / (pairs * pixels)
            if self._histogram_batch is None:
                self._histogram_batch = self._residuals(local, prior, valid)
            self._epoch_pairs += batch_size * self.trainer.world_size
        else:
            self._localize(local, prior, valid, batch["index"])
            if self._figure_pair is None:
                self._figure_pair = (local[0].detach(), prior[0].detach(), valid[0].detach())
        return loss

    def training_step(self, batch: dict, batch_idx: int) -> Tensor:
        """NLL of a batch (plus the prior's share); logs ``train/nll``, the one training loss on the dashboards."""
        return self._step(batch, "train")

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        """Held-out NLL and localization hits."""
        self._step(batch, "val")

    def _residuals(self, local: Tensor, prior: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
        with torch.no_grad():
            keep = valid & self.mask.valid_mask(local)
            residual = (local - prior)[keep]
            standardised = residual / self.mask(local).expand_as(local)[keep].sqrt()
        return residual.detach().cpu(), standardised.detach().cpu()

    def _window(self) -> tuple:
        """The central ``localization_crop`` square plus the search border, as an index of ``(..., H, W)`` images."""
        shift = self.hparams.localization_shift
        side = min(self.hparams.localization_crop + 2 * shift, *self.shape)
        top, left = (self.shape[0] - side) // 2, (self.shape[1] - side) // 2
        return (..., slice(top, top + side), slice(left, left + side))

    def held_out_sets(self, local: Tensor, prior: Tensor, valid: Tensor) -> dict[str, tuple[Tensor, Tensor, float]]:
        """The held-out sets searched at each validation: name -> ``(local, prior, variance factor)``.

        One per held-out level (:attr:`levels`: ``level_easy`` and ``level_hard`` read at the fit's start, or the
        factors ``k`` of ``localization_noise``, ``noise_x<k>``): the residuals ``local - prior`` scaled by ``k`` (the
        variance by ``k^2``). Each is cropped to the central ``localization_crop`` square plus the search border.

        A scaled local image is clipped to ``value_range``, as a sensor's output saturates (the default score reads
        those pixels as censored): strong noise on real pairs would otherwise leave the range by many widths, which
        the scores refuse. The variance factor stays ``k^2`` (clipping lowers the true variance where it bites; every
        variance map is scaled alike, so the comparison between them stays fair). A factor of 1 is the data as it is.
        """
        if self.levels is None:
            raise RuntimeError("the held-out levels are read at the fit's start (on_fit_start): none yet")
        window = self._window()
        local, prior = local[window], prior[window]
        value_range = self.hparams.value_range
        return {
            name: (amplified(local, prior, factor, value_range), prior, factor**2)
            for name, factor in self.levels.items()
        }

    def _held_out_view(self, local: Tensor, prior: Tensor, valid: Tensor) -> HeldOutView:
        """The searched window of held-out pairs, their usable pixels and the variances cropped alike."""
        window = self._window()
        learned = self.mask.variance_map().to(local.device)
        usable = valid & self.mask.valid_mask(local)  # the learned pixels are fixed from the fit's start
        truth = self.truth
        if truth is not None:
            usable = usable & truth.valid.to(local.device)
        uniform = float(learned[torch.isfinite(learned)].mean())
        true_map = None if truth is None else truth.variance.to(local.device)[window]
        return HeldOutView(local[window], prior[window], usable[window], learned[window], true_map, uniform)

    def _scores(self) -> tuple[Score, ...]:
        """The scores of the comparison: the library's default ``ECR()``, ENMI (the paper's), hard NMI, NCC."""
        bins, value_range = self.hparams.bins, tuple(self.hparams.value_range)
        return (
            ECR(bins=bins, value_range=value_range),
            ENMI(bins=bins, value_range=value_range),
            NMI(bins=bins, value_range=value_range, kernel="hard"),
            NCC(),
        )

    def _fixed(self, key: tuple, compute) -> dict:
        """``compute()``, once per ``key`` in a fit: the methods that do not depend on the mask."""
        if key not in self._fixed_results:
            self._fixed_results[key] = compute()
        return self._fixed_results[key]

    def _localize(self, local: Tensor, prior: Tensor, valid: Tensor, index: Tensor) -> None:
        world = self.trainer.world_size
        room = self.hparams.localization_pairs - self._trials * world
        if room <= 0:
            return
        take = min(local.shape[0], -(-room // world))
        local, prior, valid = local[:take], prior[:take], valid[:take]
        # Each pair's place in the held-out set: the shard sampler gives this process every world-th one.
        positions = self.trainer.global_rank + world * (self._trials + torch.arange(take))
        scores = self._scores()
        variance_scores = tuple(score for score in scores if score.uses_variance)
        shift = self.hparams.localization_shift
        with torch.no_grad():
            view = self._held_out_view(local, prior, valid)
            for set_name, (set_local, set_prior, factor) in self.held_out_sets(local, prior, valid).items():

                def fixed(set_local=set_local, set_prior=set_prior, factor=factor):
                    analytic = {} if view.truth is None else {"true": view.truth * factor}
                    return localization_trials(
                        set_local, set_prior, view.usable, analytic, max_shift=shift, scores=scores
                    )

                # The true map, NMI and NCC score the same pairs the same way at every validation of a fit: once.
                key = (set_name, tuple(index[:take].tolist()), shift, self.hparams.bins, set_local.shape[-1])
                results = localization_trials(
                    set_local,
                    set_prior,
                    view.usable,
                    {"learned": view.learned * factor, "uniform": view.uniform * factor},
                    max_shift=shift,
                    scores=variance_scores,
                    uniform_grid=tuple(self.hparams.localization_grid),
                )
                results.update(self._fixed(key, fixed))
                self._tally.add(set_name, results, positions)
        self._trials += take

    # ----- epoch ends: dashboards ---------------------------------------------------------------------------------
    def mask_errors(self) -> dict[str, float]:
        """Relative RMS errors of the learned mask against the paper's empirical mask and the truth (when known)."""
        empirical, observed = self.statistics.compute()
        valid = observed & self.mask.valid.to(observed.device)
        learned = self.mask.variance_map().to(empirical.device)
        errors = {"rel_rms_vs_empirical": relative_rms(learned, empirical, valid)}
        truth = self.truth
        if truth is not None:
            both = valid & truth.valid.to(valid.device)
            reference = truth.variance.to(empirical.device)
            errors["rel_rms_vs_truth"] = relative_rms(learned, reference, both)
            errors["empirical_rel_rms_vs_truth"] = relative_rms(empirical, reference, both)
        return errors

    def on_train_epoch_start(self) -> None:
        """Keep the first batch of the epoch for the residual histograms; start the epoch's training clock.

        The last epoch always validates, whatever ``check_val_every_n_epoch``: a run shorter than that interval still
        ends with its held-out localization, its images and its metrics in HParams.
        """
        self._histogram_batch = None
        self._clock, self._train_seconds, self._epoch_pairs = time.perf_counter(), 0.0, 0
        trainer = self.trainer
        if trainer.max_epochs is not None and trainer.current_epoch == trainer.max_epochs - 1:
            trainer.check_val_every_n_epoch = 1

    def on_validation_start(self) -> None:
        """Stop the training clock: the speed is that of training alone."""
        if not self.trainer.sanity_checking and self.trainer.state.fn == "fit":
            self._train_seconds += time.perf_counter() - self._clock

    def on_validation_end(self) -> None:
        """Restart the training clock."""
        self._clock = time.perf_counter()

    def on_train_epoch_end(self) -> None:
        """Log the mask errors, the training speed (validation left out) and the residual histograms."""
        seconds = self._train_seconds + time.perf_counter() - self._clock
        self.epoch_seconds.append(seconds)
        self.log("speed/pairs_per_second", self._epoch_pairs / seconds, sync_dist=True)
        for name, value in self.mask_errors().items():
            self.log(f"mask/{name}", value, sync_dist=True, prog_bar=name == "rel_rms_vs_empirical")
        if self._histogram_batch is not None and self.trainer.is_global_zero and self.logger is not None:
            residual, standardised = self._histogram_batch
            self.logger.experiment.add_histogram("residuals/raw", residual, self.global_step)
            self.logger.experiment.add_histogram("residuals/standardised", standardised, self.global_step)

    def on_validation_epoch_start(self) -> None:
        """Start the held-out tally: every method of every held-out set, by the pair's place in the held-out set.

        The first validation of a fit that reads its held-out levels from the data reads them first.
        """
        self._trials, self._figure_pair = 0, None
        if self.levels is None:
            self.read_levels()
            self._log_layout()
        variance_names = ["learned", "uniform"] + (["true"] if self.truth is not None else [])
        methods = trial_methods(self._scores(), variance_names, tuple(self.hparams.localization_grid))
        names = [f"{held_out}/{method}" for held_out in (self.levels or {}) for method in methods]
        self._tally = HeldOutTally(len(self.trainer.datamodule.val_set), names)

    def on_validation_epoch_end(self) -> None:
        """Sum the held-out tally over processes; log the shares, the margins, the answer and the figures."""
        if self.trainer.sanity_checking:
            return
        strategy = self.trainer.strategy
        tally = self._tally.reduce(lambda tensor: strategy.reduce(tensor.to(self.device), reduce_op="sum"))
        self.held_out = tally.summary()
        rates, margins, pairs = self.held_out.rates, self.held_out.margins, self.held_out.pairs
        for name in sorted(rates):
            self.log(f"localization/{name}", rates[name], sync_dist=False)
            if math.isfinite(margins[name]):
                self.log(f"localization_z/{name}", margins[name], sync_dist=False)
        if rates and isinstance(self.logger, MaskLogger):
            self.logger.log_answer(rates, self.global_step)
        if self.trainer.is_global_zero and self._figure_pair is not None and self.logger is not None:
            figure = self.figure()
            self.logger.experiment.add_figure("masks", figure, self.global_step)
            if pairs > 0:
                nested: dict[str, dict[str, float]] = {}
                for name, rate in rates.items():
                    held_out, method = name.split("/")
                    nested.setdefault(held_out, {})[method] = rate
                shift = self.hparams.localization_shift
                title = f"epoch {self.current_epoch}: held-out pairs searched within ±{shift} pixels by localize"
                figure = localization_figure(nested, pairs, title=title)
                self.logger.experiment.add_figure("localization", figure, self.global_step)

    def figure(self):
        """The mask figure (learned, empirical, truth, one held-out residual) at the current state."""
        empirical, _ = self.statistics.compute()
        truth = self.truth
        residual = masked_residual(*self._figure_pair) if self._figure_pair is not None else None
        errors = self.mask_errors()
        scores = f"learned vs empirical {100 * errors['rel_rms_vs_empirical']:.1f} %"
        if "rel_rms_vs_truth" in errors:
            floor = errors["empirical_rel_rms_vs_truth"]
            scores += f", vs truth {100 * errors['rel_rms_vs_truth']:.1f} % (floor {100 * floor:.1f} %)"
        source = f"{truth.flavour}-like, " if truth is not None and truth.flavour in FLAVOURS else ""
        pairs = int(self.statistics.count.max())
        title = f"{source}{pairs} pairs, epoch {self.current_epoch}; relative RMS error:\n{scores}"
        return mask_figure(
            self.mask.variance_map(),
            empirical,
            None if truth is None else truth.variance,
            residual,
            title=title,
        )
