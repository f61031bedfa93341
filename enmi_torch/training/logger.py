"""``MaskLogger``: the fit-mask dashboards open on the answer.

TensorBoard's logger with, for this command: runs named by their data (``runs/fit_mask/lidar_0``, not
``version_0``), no ``epoch`` staircase, no ``hp_metric = -1``; a custom-scalars layout (the Custom Scalars tab) that
opens on the answer, per held-out set one chart of the library's default score (ECR) with the learned mask, the true
variance, one uniform variance and the best uniform variance, and ENMI with its best uniform variance, each line its
own colour (a sub-run per method), then the mask's error against its empirical floor, and every score and variance
folded below; and, at the end of a fit, the hyperparameters with the run's real final metrics, the answer's first
(the HParams tab reads each metric's last value).
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from lightning.fabric.utilities.logger import _convert_params, _flatten_dict
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.utilities import rank_zero_only

LAYOUT_TAG = "custom_scalars__config__"
# The hyperparameters that tell runs apart, shown in the HParams tab where a run changed them from their defaults.
SHOWN = ("form", "smoothness", "match_intensity", "train_pairs", "size", "noise_std", "lr")


def run_name(root: str | None, flavour: str) -> str:
    """What a run is named after: the pairs folder's name, or the synthetic flavour (``"lidar"``)."""
    if root is None:
        return flavour
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(root).resolve().name).strip("._")
    return name or "pairs"


def next_version(folder: str | Path, name: str) -> str:
    """Create and return ``<name>_<n>``: the first free ``n`` above the existing ``<name>_<n>`` folders (0 for none).

    The folder is taken with ``os.mkdir``, which fails if another process took it first (runs started at once): the
    next number is tried then, so no two runs share a folder.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    taken = [
        int(match.group(1))
        for path in folder.iterdir()
        if (match := re.fullmatch(rf"{re.escape(name)}_(\d+)", path.name))
    ]
    number = max(taken, default=-1) + 1
    while True:
        try:
            os.mkdir(folder / f"{name}_{number}")
        except FileExistsError:
            number += 1
            continue
        return f"{name}_{number}"


# The Custom Scalars category that answers the run's question, and the tag of its chart per held-out set.
ANSWER = (
    "with the default score, does the learned mask beat a uniform variance (and ENMI)? share of held-out pairs located,"
    " per noise level"
)


def answer_tag(held_out: str) -> str:
    """The tag of the answer chart of one held-out set; each of its lines is a sub-run named by the method."""
    return f"answer/{held_out}"


def layout(sets: Mapping[str, str], masked_truth: bool) -> dict[str, dict[str, tuple[str, list[str]]]]:
    """The Custom Scalars layout: category -> chart title -> ``("Multiline", [tag regex, ...])``.

    ``sets``: the held-out sets, hardest first, each with its label (``"level_hard (x24)"``: the name and its noise
    factor); ``masked_truth``: whether the true variance is known. The first category answers the question: per
    held-out set, one chart whose lines are :data:`~enmi_torch.training.held_out.ANSWER_METHODS`, each logged to its
    own sub-run (TensorBoard colours a chart's lines by run, so each method gets its own colour, named in the chart's
    legend).
    """
    from enmi_torch.training.held_out import ANSWER_METHODS

    lines = [method for method in ANSWER_METHODS if masked_truth or not method.endswith("_true")]
    answer = {
        f"{label}: {', '.join(lines)}": ("Multiline", [rf"^{re.escape(answer_tag(name))}$"])
        for name, label in sets.items()
    }
    every = {
        f"{label}: every score and variance": ("Multiline", [rf"localization/{re.escape(name)}/.*"])
        for name, label in sets.items()
    }
    mask = {}
    if masked_truth:
        mask["learned mask vs the true variance, and the empirical mask's error (its floor)"] = (
            "Multiline",
            ["mask/rel_rms_vs_truth", "mask/empirical_rel_rms_vs_truth"],
        )
    mask["learned mask vs the paper's empirical mask (convergence)"] = ("Multiline", ["mask/rel_rms_vs_empirical"])
    margins = {
        f"{label}: margin of the true shift (z-score), every score and variance": (
            "Multiline",
            [rf"localization_z/{re.escape(name)}/.*"],
        )
        for name, label in sets.items()
    }
    training = {
        "Gaussian NLL per valid pixel, training and held-out": ("Multiline", ["train/nll", "val/nll"]),
        "training speed (validation left out)": ("Multiline", ["speed/pairs_per_second"]),
    }
    return {
        ANSWER: answer,
        "the learned mask": mask,
        "every score and variance: share of held-out pairs located": every,
        "localization margins": margins,
        "training": training,
    }


def layout_summary(categories: Mapping[str, Mapping[str, tuple[str, list[str]]]], closed: Iterable[str] = ()):
    """The ``custom_scalars__config__`` summary of a layout, categories in ``closed`` folded."""
    from tensorboard.compat.proto.summary_pb2 import Summary, SummaryMetadata
    from tensorboard.compat.proto.tensor_pb2 import TensorProto
    from tensorboard.compat.proto.tensor_shape_pb2 import TensorShapeProto
    from tensorboard.plugins.custom_scalar import layout_pb2

    closed = set(closed)
    proto = layout_pb2.Layout(
        category=[
            layout_pb2.Category(
                title=title,
                closed=title in closed,
                chart=[
                    layout_pb2.Chart(title=chart, multiline=layout_pb2.MultilineChartContent(tag=list(tags)))
                    for chart, (_, tags) in charts.items()
                ],
            )
            for title, charts in categories.items()
            if charts
        ]
    )
    tensor = TensorProto(dtype="DT_STRING", string_val=[proto.SerializeToString()], tensor_shape=TensorShapeProto())
    metadata = SummaryMetadata(plugin_data=SummaryMetadata.PluginData(plugin_name="custom_scalars"))
    return Summary(value=[Summary.Value(tag=LAYOUT_TAG, tensor=tensor, metadata=metadata)])


class MaskLogger(TensorBoardLogger):
    """:class:`~lightning.pytorch.loggers.TensorBoardLogger` for ``enmi-fit-mask``'s dashboards.

    Args are TensorBoardLogger's; ``default_hp_metric`` is off (the real metrics go to HParams at the end of a fit,
    :meth:`log_final_metrics`).
    """

    def __init__(self, *args: Any, default_hp_metric: bool = False, **kwargs: Any) -> None:
        super().__init__(*args, default_hp_metric=default_hp_metric, **kwargs)
        self._answer_writers: dict[str, Any] = {}

    @rank_zero_only
    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        """Every metric but Lightning's ``epoch`` counter (a staircase that answers nothing)."""
        super().log_metrics({key: value for key, value in metrics.items() if key != "epoch"}, step)

    @rank_zero_only
    def log_layout(self, sets: Mapping[str, str], masked_truth: bool) -> None:
        """Write the Custom Scalars layout (:func:`layout`); all but the answer and the mask start folded."""
        categories = layout(sets, masked_truth)
        summary = layout_summary(categories, closed=list(categories)[2:])
        self.experiment._get_file_writer().add_summary(summary)

    @rank_zero_only
    def log_answer(self, rates: Mapping[str, float], step: int) -> None:
        """Log the answer's lines: ``rates`` (``"<set>/<method>"`` -> share) of the answer's methods, one sub-run each.

        The sub-run ``<run>/<method>`` holds the tag ``answer/<set>``: one chart per set, one colour per method.
        """
        from torch.utils.tensorboard import SummaryWriter

        from enmi_torch.training.held_out import ANSWER_METHODS

        for name, rate in rates.items():
            held_out, method = name.split("/")
            if method not in ANSWER_METHODS:
                continue
            if method not in self._answer_writers:
                self._answer_writers[method] = SummaryWriter(str(Path(self.log_dir) / method))
            self._answer_writers[method].add_scalar(answer_tag(held_out), rate, step)
        for writer in self._answer_writers.values():
            writer.flush()

    @rank_zero_only
    def finalize(self, status: str) -> None:
        """Close the answer's sub-run writers too."""
        super().finalize(status)
        for writer in self._answer_writers.values():
            writer.close()
        self._answer_writers = {}

    @rank_zero_only
    def log_final_metrics(
        self,
        metrics: Sequence[str],
        leading: Mapping[str, Any] | None = None,
        defaults: Mapping[str, Any] | None = None,
    ) -> None:
        """The hyperparameters with these metric tags: the HParams tab shows each tag's last logged value.

        The hyperparameters are ``leading`` (the data, the epochs) and those of ``SHOWN`` that differ from
        ``defaults``: TensorBoard ticks only the first five hyperparameters and five metrics, so a run with the default
        settings opens on its answer (the first metrics) on the first screen. Every hyperparameter is in the run's
        ``hparams.yaml`` and ``config.yaml``.
        """
        from torch.utils.tensorboard.summary import hparams

        stored = self._sanitize_params(_flatten_dict(_convert_params(dict(self.hparams))))
        defaults = dict(defaults or {})
        params = dict(leading or {})
        params.update(
            {
                key: stored[key]
                for key in SHOWN
                if key in stored and key not in params and (key not in defaults or stored[key] != defaults[key])
            }
        )
        experiment, start, end = hparams(params, dict.fromkeys(metrics, 0.0))
        writer = self.experiment._get_file_writer()
        for summary in (experiment, start, end):
            writer.add_summary(summary)
        writer.flush()
