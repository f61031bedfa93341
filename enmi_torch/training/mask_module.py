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
within one pixel by a whole-image search, the localization yardstick's protocol) and
``localization_z/<held-out set>/<method>`` (the mean z-score of the true shift's score among the others: the margin)
for ECR and ENMI with the learned mask (``*_learned``), the true field (``*_true``, synthetic data) and the
uniform controls (``*_uniform``: the learned mask's mean; ``enmi_best_uniform``: the best of the mean times
``localization_grid``), hard NMI and NCC. The held-out sets are the validation pairs with their residuals
``local - prior`` scaled by each of ``localization_noise`` (``noise_x16``: 16 times the noise, 256 times the
variance; every variance map is scaled alike), so that the methods part ways; the methods that do not depend on the
mask are scored at a fit's first validation and reused (the same pairs give the same scores).
``speed/pairs_per_second`` (training only, validation left out); the mask figure; histograms of raw and
standardised residuals.
"""

from __future__ import annotations

import inspect
import math
import time
from collections.abc import Sequence

import numpy as np
import torch
from lightning.pytorch import LightningModule
from torch import Tensor

from enmi_torch.data import match_intensity
from enmi_torch.data.truth import FLAVOURS
from enmi_torch.scores import ECR, ENMI, NCC, NMI, Score
from enmi_torch.training.fit_checks import check_model_options
from enmi_torch.training.localization_figure import ANSWER_METHODS, OTHER_METHODS, held_out_order, localization_figure
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


def localization_trials(
    local: Tensor,
    prior: Tensor,
    valid: Tensor,
    variances: dict[str, Tensor | float],
    *,
    max_shift: int,
    scores: Sequence[Score],
    uniform_grid: tuple[float, ...] = (),
    grid_score: Score | None = None,
) -> dict[str, tuple[int, float]]:
    """Whole-image localization of aligned pairs, the yardstick's protocol: hits and peak z-scores.

    Each pair's local image, less a border of ``max_shift`` pixels, is searched in its prior image at every shift in
    ``[-max_shift, max_shift]^2`` (the scores' FFT surfaces); the pair is located when the best shift is within one
    pixel of the zero shift. The peak z-score, ``(score at zero shift - mean) / std`` over the shifts more than one
    pixel away, measures the margin where every method locates the pair.

    Args:
        local: ``(B, 1, H, W)``.
        prior: ``(B, 1, H, W)``, aligned with ``local``.
        valid: bool ``(B, 1, H, W)``, pixels usable by every method.
        variances: name -> ``(H, W)`` variance map or a number (one uniform variance); each score that uses a
            variance is scored with each (methods ``"<score name>_<variance name>"``, e.g. ``"ecr_learned"``).
        max_shift: largest shift in pixels.
        scores: the scores searched (e.g. ``ECR(bins=32)``, ``ENMI(bins=32)``, ``NMI(bins=32)``, ``NCC()``); those
            without a variance once each (method ``"<score name>"``).
        uniform_grid: factors for the best-uniform control: ``grid_score`` at the variance named ``"uniform"`` times
            each factor (``"<grid score name>_uniform_x<factor>"``).
        grid_score: the score of the best-uniform control (needed with ``uniform_grid``).

    Returns:
        Method -> ``(hits, sum of peak z-scores)`` over the pairs, for the methods above.
    """
    if uniform_grid and grid_score is None:
        raise ValueError(f"uniform_grid needs a grid_score, got uniform_grid={uniform_grid!r} and grid_score=None")
    height, width = local.shape[-2:]
    inner = (..., slice(max_shift, height - max_shift), slice(max_shift, width - max_shift))
    crop, crop_valid = local[inner].float(), valid[inner]
    window = prior.float()
    surfaces = {}
    for name, variance in variances.items():
        if isinstance(variance, Tensor):
            variance = variance[inner].float()
        for score in scores:
            if score.uses_variance:
                surfaces[f"{score.name}_{name}"] = score.surface(crop, window, variance, captured_mask=crop_valid)
        if name == "uniform":
            for factor in uniform_grid:
                surface = grid_score.surface(crop, window, variance * factor, captured_mask=crop_valid)
                surfaces[f"{grid_score.name}_uniform_x{factor:g}"] = surface
    for score in scores:
        if not score.uses_variance:
            surfaces[score.name] = score.surface(crop, window, captured_mask=crop_valid)
    span = 2 * max_shift + 1
    offsets = torch.arange(span, device=local.device) - max_shift
    far = (offsets.abs().view(-1, 1) > 1) | (offsets.abs().view(1, -1) > 1)
    results = {}
    for method, surface in surfaces.items():
        score = surface.score.double()
        peak = score.flatten(1).argmax(1)
        rows, cols = peak // span - max_shift, peak % span - max_shift
        hits = int(((rows.abs() <= 1) & (cols.abs() <= 1)).sum())
        others = score[:, far]
        if others.shape[1] < 2:  # max_shift 1 leaves no shift farther than a pixel: no margin to measure
            results[method] = (hits, math.nan)
            continue
        z = (score[:, max_shift, max_shift] - others.mean(1)) / others.std(1).clamp_min(1e-12)
        results[method] = (hits, float(z.sum()))
    return results


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
        localization_noise: factors of the held-out noise, one held-out set each (1: as it is).
        localization_grid: factors of the uniform variance tried by the best-uniform ENMI control.
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
        localization_noise: tuple[float, ...] = (1.0, 16.0, 32.0),
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
        localization_noise = [float(factor) for factor in localization_noise]
        localization_grid = [float(factor) for factor in localization_grid]
        self.save_hyperparameters()
        self.shape = (shape[0], shape[1])
        self.mask: LearnedVariance | None = None
        self.statistics = EmpiricalVariance(self.shape)
        self.register_buffer("statistics_ready", torch.tensor(False))
        self._hits: dict[str, float] = {}
        self._z_sums: dict[str, float] = {}
        self._trials = 0
        self._histogram_batch: tuple[Tensor, Tensor] | None = None
        self._clock, self._train_seconds, self._epoch_pairs = 0.0, 0.0, 0
        self.epoch_seconds: list[float] = []
        self._figure_pair: tuple[Tensor, Tensor, Tensor] | None = None
        self._fixed_results: dict[tuple, dict[str, tuple[int, float]]] = {}

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
        if bool(self.statistics_ready):
            return
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
        """Lay out the Custom Scalars tab: the held-out sets, hardest first, and the mask's errors."""
        if isinstance(self.logger, MaskLogger):
            noise = sorted(self.hparams.localization_noise, reverse=True) if self.hparams.localization_pairs else []
            self.logger.log_layout([f"noise_x{factor:g}" for factor in noise], self.truth is not None)

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

    def held_out_sets(self, local: Tensor, prior: Tensor, valid: Tensor) -> dict[str, tuple[Tensor, Tensor, float]]:
        """The held-out sets searched at each validation: name -> ``(local, prior, variance factor)``.

        One per factor ``k`` of ``localization_noise``: the residuals ``local - prior`` scaled by ``k`` (the variance by
        ``k^2``), named ``noise_x<k>``. Each is cropped to the central ``localization_crop`` square plus the search
        border. Another kind of held-out pairs (scene changes, say) is one more entry.

        A scaled local image is clipped to ``value_range``, as a sensor's output saturates: strong noise on real pairs
        would otherwise leave the range by many widths, which the scores refuse. The variance factor stays ``k^2``
        (clipping lowers the true variance where it bites; every variance map is scaled alike, so the comparison
        between them stays fair). ``noise_x1`` is the data as it is.
        """
        shift = self.hparams.localization_shift
        side = min(self.hparams.localization_crop + 2 * shift, *self.shape)
        top, left = (self.shape[0] - side) // 2, (self.shape[1] - side) // 2
        window = (..., slice(top, top + side), slice(left, left + side))
        local, prior = local[window], prior[window]
        low, high = self.hparams.value_range
        return {
            f"noise_x{factor:g}": (
                local if factor == 1 else (prior + factor * (local - prior)).clamp(low, high),
                prior,
                factor**2,
            )
            for factor in self.hparams.localization_noise
        }

    def _fixed(self, key: tuple, compute) -> dict[str, tuple[int, float]]:
        """``compute()``, once per ``key`` in a fit: the methods that do not depend on the mask."""
        if key not in self._fixed_results:
            self._fixed_results[key] = compute()
        return self._fixed_results[key]

    def _localize(self, local: Tensor, prior: Tensor, valid: Tensor, index: Tensor) -> None:
        room = self.hparams.localization_pairs - self._trials * self.trainer.world_size
        if room <= 0:
            return
        take = min(local.shape[0], -(-room // self.trainer.world_size))
        local, prior, valid = local[:take], prior[:take], valid[:take]
        bins, value_range = self.hparams.bins, tuple(self.hparams.value_range)
        variance_scores = (ECR(bins=bins, value_range=value_range), ENMI(bins=bins, value_range=value_range))
        shift = self.hparams.localization_shift
        with torch.no_grad():
            learned = self.mask.variance_map().to(local.device)
            usable = valid & self.mask.valid_mask(local)  # the learned pixels are fixed from the fit's start
            truth = self.truth
            if truth is not None:
                usable = usable & truth.valid.to(local.device)
            sets = self.held_out_sets(local, prior, usable)
            side = next(iter(sets.values()))[0].shape[-1]
            top, left = (self.shape[0] - side) // 2, (self.shape[1] - side) // 2
            window = (..., slice(top, top + side), slice(left, left + side))
            usable, learned = usable[window], learned[window]
            uniform = float(learned[torch.isfinite(learned)].mean())
            for set_name, (set_local, set_prior, factor) in sets.items():

                def fixed(set_local=set_local, set_prior=set_prior, factor=factor):
                    analytic = {} if truth is None else {"true": truth.variance.to(local.device)[window] * factor}
                    return localization_trials(
                        set_local,
                        set_prior,
                        usable,
                        analytic,
                        max_shift=shift,
                        scores=(*variance_scores, NMI(bins=bins, value_range=value_range, kernel="hard"), NCC()),
                    )

                # The true map, NMI and NCC score the same pairs the same way at every validation of a fit: once.
                key = (set_name, tuple(index[:take].tolist()), shift, bins, side)
                results = localization_trials(
                    set_local,
                    set_prior,
                    usable,
                    {"learned": learned * factor, "uniform": uniform * factor},
                    max_shift=shift,
                    scores=variance_scores,
                    uniform_grid=tuple(self.hparams.localization_grid),
                    grid_score=variance_scores[1],
                )
                results.update(self._fixed(key, fixed))
                for method, (hits, z_sum) in results.items():
                    name = f"{set_name}/{method}"
                    self._hits[name] = self._hits.get(name, 0) + hits
                    self._z_sums[name] = self._z_sums.get(name, 0.0) + z_sum
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
        """Reset the localization counts."""
        self._hits, self._z_sums, self._trials, self._figure_pair = {}, {}, 0, None

    def on_validation_epoch_end(self) -> None:
        """Sum the localization counts over processes, log the accuracies and the mask figure."""
        if self.trainer.sanity_checking:
            return
        names = sorted(self._hits)
        totals = [self._hits[name] for name in names] + [self._z_sums[name] for name in names] + [self._trials]
        totals = torch.tensor(totals, dtype=torch.float64)
        totals = self.trainer.strategy.reduce(totals.to(self.device), reduce_op="sum")
        pairs = float(totals[-1])
        if pairs > 0:
            rates = {name: float(totals[index]) / pairs for index, name in enumerate(names)}
            margins = {name: float(totals[len(names) + index]) / pairs for index, name in enumerate(names)}
            for set_name in sorted({name.split("/")[0] for name in names}):
                others = [f"{set_name}/{method}" for method in OTHER_METHODS]
                for best_name, group in (
                    ("enmi_best_uniform", [name for name in names if name.startswith(f"{set_name}/enmi_uniform")]),
                    ("best_other", [name for name in others if name in rates]),
                ):
                    best = max(group, key=lambda name: (rates[name], margins[name]))
                    rates[f"{set_name}/{best_name}"], margins[f"{set_name}/{best_name}"] = rates[best], margins[best]
            for name in sorted(rates):
                if "/enmi_uniform_x" in name:
                    continue
                self.log(f"localization/{name}", rates[name], sync_dist=False)
                if math.isfinite(margins[name]):
                    self.log(f"localization_z/{name}", margins[name], sync_dist=False)
            if isinstance(self.logger, MaskLogger):
                self.logger.log_answer(rates, self.global_step)
        if self.trainer.is_global_zero and self._figure_pair is not None and self.logger is not None:
            figure = self.figure()
            self.logger.experiment.add_figure("masks", figure, self.global_step)
            if pairs > 0:
                nested: dict[str, dict[str, float]] = {}
                for name, rate in rates.items():
                    held_out, method = name.split("/")
                    if not method.startswith("enmi_uniform_x"):
                        nested.setdefault(held_out, {})[method] = rate
                shift = self.hparams.localization_shift
                title = f"epoch {self.current_epoch}: held-out pairs searched within ±{shift} pixels"
                figure = localization_figure(nested, int(pairs), title=title)
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
