"""``enmi-reproduce-paper`` (also ``python -m enmi_torch.cli.reproduce_paper``): the paper's Fig. simPerformance.

Probability of error of NMI and ENMI against the noise power N0, simulated with the library's ``nmi`` and ``enmi``
at every N0 of the paper's plot; ``--help`` says what it writes and prints.
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import matplotlib

matplotlib.use("Agg")
import jsonargparse
import matplotlib.pyplot as plt
import torch
from jsonargparse.typing import Path_fr
from tqdm import tqdm

from enmi_torch import RoadCamera
from enmi_torch.simulation import SCORES, ErrorRates, error_rates, road_tiles
from enmi_torch.utils.command import check_text_files, dashed_aliases, parser_error, run_command
from enmi_torch.utils.resources import config_file

PROG = "enmi-reproduce-paper"
DESCRIPTION = f"""\
Reproduce the paper's Fig. simPerformance: the probability of a wrong match against the noise power N0, for NMI
and for ENMI with three weightings, 10,000 trials at each of the 141 N0 of the paper's plot (about 2 minutes on 2
CPU cores; --scores '[nmi, enmi_mass]' takes a quarter of that).

It simulates section "Simulated Performance" with configs/paper_simulation.yaml: 66 road tiles seen by the paper's
camera, amplitudes N(128, 32^2), an independent candidate, noise variance N0 / A~ per tile. It writes
paper_simulation.csv (our error rates, their standard errors, the paper's points) and paper_simulation.png (ours
over the paper's) to --output-dir (refusing to replace an earlier run's unless --overwrite true), and prints the
run time and the deviations from the paper as Markdown tables.

examples:
  {PROG}                                              # also: python -m enmi_torch.cli.reproduce_paper
  {PROG} --scores '[nmi, enmi_mass]' --trials 2000    # two curves, fewer trials
  {PROG} --output-dir runs/paper --overwrite true     # replace an earlier run's figure and CSV there
  {PROG} --tensorboard runs/paper_tensorboard         # also log every point and the figure

Every key of the config is an option, its underscores written as dashes (output_dir: --output-dir). Relative paths
in a config file (camera_config, paper_points) are read from the config file's folder, on the command line from
the current folder. --debug shows the full traceback of an error instead of one line."""


class _Formatter(jsonargparse.DefaultHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """jsonargparse's help (types, defaults) with the description's line breaks kept."""


class _Parser(jsonargparse.ArgumentParser):
    def error(self, message: str, ex: Exception | None = None):
        parser_error(self, message)


NMI_TOLERANCE = 0.03
LABELS = {
    "nmi": "NMI (ours)",
    "enmi_mass": "ENMI, mass weights (ours)",
    "enmi_density": "ENMI, density weights (ours)",
    "enmi_mass_prior": "ENMI, mass weights + amplitude prior (ours)",
}
STYLES = {
    "nmi": {"color": "tab:blue", "linestyle": "--"},
    "enmi_mass": {"color": "black", "linestyle": "-"},
    "enmi_density": {"color": "tab:green", "linestyle": "-."},
    "enmi_mass_prior": {"color": "tab:orange", "linestyle": ":"},
}


def build_parser() -> jsonargparse.ArgumentParser:
    """The command's options, with configs/paper_simulation.yaml as the defaults."""
    defaults = config_file("paper_simulation.yaml")
    parser = _Parser(
        prog=PROG, description=DESCRIPTION, default_config_files=[str(defaults)], formatter_class=_Formatter
    )
    parser.add_argument(
        "--config", action=jsonargparse.ActionConfigFile, help="a YAML config like configs/paper_simulation.yaml"
    )
    parser.add_argument(
        "--camera-config", type=Path_fr, default=Path_fr(config_file("camera/paper.yaml")), help="the road camera"
    )
    parser.add_argument(
        "--row-counts", type=list[int], default=[5, 5, 7, 7, 9, 9, 11, 13], help="tiles per row, nearest first"
    )
    parser.add_argument("--tile-size", type=float, default=20.0, help="side of a tile (cm)")
    parser.add_argument("--nearest-distance", type=float, default=40.0, help="near edge of the nearest row (cm)")
    parser.add_argument("--amplitude-mean", type=float, default=128.0, help="mean of the tile amplitudes")
    parser.add_argument("--amplitude-std", type=float, default=32.0, help="standard deviation of the amplitudes")
    parser.add_argument("--bins", type=int, default=32, help="equal bins over value_range")
    parser.add_argument("--value-range", type=tuple[float, float], default=(0.0, 256.0), help="range of the bins")
    parser.add_argument("--trials", type=int, default=10_000, help="trials per N0")
    parser.add_argument("--seed", type=int, default=0, help="seed of the common random numbers")
    parser.add_argument("--scores", type=list[str], default=list(SCORES), help=f"scores to simulate, of {list(SCORES)}")
    parser.add_argument(
        "--paper-points",
        type=Path_fr,
        default=Path_fr(config_file("paper_points.csv")),
        help="the paper's plotted points (CSV)",
    )
    parser.add_argument(
        "--output-dir", type=str, default="runs/paper_simulation", help="folder for the CSV and the figure"
    )
    parser.add_argument(
        "--overwrite", type=bool, default=False, help="replace the CSV and figure of an earlier run in --output-dir"
    )
    parser.add_argument("--chunk-trials", type=int, default=96, help="trials per scoring call")
    parser.add_argument("--dtype", type=Literal["float32", "float64"], default="float32", help="precision")
    parser.add_argument("--workers", type=int, default=1, help="N0 points scored at once (threads)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads per worker")
    parser.add_argument("--tensorboard", type=str | None, default=None, help="log to this TensorBoard directory")
    return parser


# Every option of the config, as the dashed flag's hidden alias (--output_dir for --output-dir).
CONFIG_KEYS = (
    "camera_config",
    "row_counts",
    "tile_size",
    "nearest_distance",
    "amplitude_mean",
    "amplitude_std",
    "value_range",
    "paper_points",
    "output_dir",
    "chunk_trials",
    "overwrite",
)
OUTPUTS = ("paper_simulation.csv", "paper_simulation.png")


def read_paper_points(path: Path) -> dict[str, list[float]]:
    """The paper's plotted points: columns ``noise_power``, ``nmi``, ``enmi``."""
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    if not rows or set(rows[0]) != {"noise_power", "nmi", "enmi"}:
        raise ValueError(
            f"{path} must be a CSV with columns noise_power, nmi, enmi (the paper's plotted points, as in the "
            "default config's paper_points.csv)"
        )
    return {column: [float(row[column]) for row in rows] for column in ("noise_power", "nmi", "enmi")}


def binomial_stderr(rate: float, trials: int) -> float:
    """Standard error of a rate estimated from ``trials`` trials."""
    return math.sqrt(rate * (1 - rate) / trials)


def deviation_rows(result: ErrorRates, paper: dict[str, list[float]]) -> list[list[str]]:
    """One row per score: its largest deviation from the paper's curve and whether the criterion holds."""
    rows = []
    n0 = paper["noise_power"]
    for score, rates in result.rates.items():
        ours = rates.tolist()
        if score == "nmi":
            deviation = [mine - theirs for mine, theirs in zip(ours, paper["nmi"], strict=True)]
            worst = max(range(len(n0)), key=lambda index: abs(deviation[index]))
            inside = sum(abs(value) <= NMI_TOLERANCE for value in deviation)
            rows.append(
                [
                    "NMI vs paper NMI",
                    f"{deviation[worst]:+.4f}",
                    f"{n0[worst]:g}",
                    f"{ours[worst]:.4f}",
                    f"{paper['nmi'][worst]:.4f}",
                    f"mean {statistics.fmean(deviation):+.4f}, sd {statistics.pstdev(deviation):.4f}",
                    f"within ±{NMI_TOLERANCE} at {inside}/{len(n0)}",
                ]
            )
            continue
        excess = [mine - theirs for mine, theirs in zip(ours, paper["enmi"], strict=True)]
        stderr = [
            math.hypot(binomial_stderr(mine, result.trials), binomial_stderr(theirs, 10_000))
            for mine, theirs in zip(ours, paper["enmi"], strict=True)
        ]
        worst = max(range(len(n0)), key=lambda index: excess[index])
        below = sum(value <= 2 * error for value, error in zip(excess, stderr, strict=True))
        largest_z = max(value / error for value, error in zip(excess, stderr, strict=True) if error > 0)
        rows.append(
            [
                f"{LABELS[score].removesuffix(' (ours)')} vs paper ENMI",
                f"{excess[worst]:+.4f}",
                f"{n0[worst]:g}",
                f"{ours[worst]:.4f}",
                f"{paper['enmi'][worst]:.4f}",
                f"largest (ours - paper) / SE {largest_z:+.1f}",
                f"at or below paper + 2 SE at {below}/{len(n0)}",
            ]
        )
    return rows


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def write_csv(path: Path, result: ErrorRates, paper: dict[str, list[float]]) -> None:
    """Our rates and standard errors beside the paper's points, one row per N0."""
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        scores = list(result.rates)
        writer.writerow(["noise_power", "paper_nmi", "paper_enmi", *scores, *(f"{score}_stderr" for score in scores)])
        for index, noise_power in enumerate(paper["noise_power"]):
            rates = [result.rates[score][index].item() for score in scores]
            errors = [result.standard_error(score)[index].item() for score in scores]
            writer.writerow(
                [
                    noise_power,
                    paper["nmi"][index],
                    paper["enmi"][index],
                    *(f"{rate:.4f}" for rate in rates),
                    *(f"{error:.4f}" for error in errors),
                ]
            )


def draw_figure(result: ErrorRates, paper: dict[str, list[float]]):
    """Our curves over the paper's points, log N0 axis."""
    figure, axes = plt.subplots(figsize=(8, 5), layout="constrained")
    axes.plot(paper["noise_power"], paper["nmi"], "o", color="tab:blue", mfc="none", ms=4, label="NMI (paper)")
    axes.plot(paper["noise_power"], paper["enmi"], "s", color="black", mfc="none", ms=4, label="ENMI (paper)")
    for score, rates in result.rates.items():
        axes.plot(result.noise_powers.tolist(), rates.tolist(), lw=1.8, label=LABELS[score], **STYLES[score])
    axes.set_xscale("log")
    axes.set_ylim(-0.02, 0.6)
    axes.set_xlabel("Power spectral density, $N_0$")
    axes.set_ylabel("Probability of error")
    axes.set_title(f"Fig. simPerformance: 66 tiles, {result.trials:,} trials per $N_0$, ours over the paper's points")
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(loc="upper left", fontsize=8)
    return figure


def main(argv: Sequence[str] | None = None) -> None:
    """Console entry point: ``enmi-reproduce-paper --help``."""
    run_command(PROG, reproduce_paper, argv)


def reproduce_paper(argv: Sequence[str]) -> None:
    """The command with these arguments."""
    check_text_files(argv, "--config")
    args = build_parser().parse_args(dashed_aliases(argv, [key.replace("_", "-") for key in CONFIG_KEYS]))
    for flag, value in (("--threads", args.threads), ("--workers", args.workers)):
        if value < 1:
            raise ValueError(f"{flag} must be an int >= 1, got {value}")
    if not args.scores:
        raise ValueError(f"--scores must name at least one score of {list(SCORES)}, got []")
    output_dir = Path(args.output_dir)
    earlier = [name for name in OUTPUTS if (output_dir / name).exists()]
    if earlier and not args.overwrite:
        raise ValueError(
            f"--output-dir {str(output_dir)!r} already holds {', '.join(earlier)} of an earlier run; choose another "
            "--output-dir, or pass --overwrite true to replace them"
        )
    torch.set_num_threads(args.threads)
    paper = read_paper_points(Path(args.paper_points.absolute))
    try:
        camera = RoadCamera.from_yaml(args.camera_config.absolute)
    except ValueError as error:
        raise ValueError(f"--camera-config: {error}") from None
    tiles = road_tiles(camera, args.row_counts, args.tile_size, args.nearest_distance)
    output_dir.mkdir(parents=True, exist_ok=True)
    writer = None
    if args.tensorboard is not None:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(args.tensorboard)
        writer.add_text("config", f"```\n{build_parser().dump(args)}\n```")

    bars = []  # opened at the first point, so that a refused option is not printed after an empty bar

    def progress(point: int, rates: dict[str, float], seconds: float) -> None:
        if not bars:
            bars.append(tqdm(total=len(paper["noise_power"]), unit="N0", desc="simulating", mininterval=1.0))
        bars[0].update()
        if writer is not None:
            writer.add_scalar("noise_power", paper["noise_power"][point], point)
            writer.add_scalars(
                "error_rate", {**rates, "paper_nmi": paper["nmi"][point], "paper_enmi": paper["enmi"][point]}, point
            )
            writer.add_scalar("seconds_per_point", seconds, point)

    started = time.perf_counter()
    result = error_rates(
        tiles.area,
        paper["noise_power"],
        trials=args.trials,
        scores=args.scores,
        seed=args.seed,
        amplitude_mean=args.amplitude_mean,
        amplitude_std=args.amplitude_std,
        bins=args.bins,
        value_range=tuple(args.value_range),
        chunk_trials=args.chunk_trials,
        dtype=getattr(torch, args.dtype),
        workers=args.workers,
        progress=progress,
    )
    wall = time.perf_counter() - started
    bars[0].close()

    points = len(paper["noise_power"])
    write_csv(output_dir / "paper_simulation.csv", result, paper)
    figure = draw_figure(result, paper)
    figure.savefig(output_dir / "paper_simulation.png", dpi=110)
    if writer is not None:
        writer.add_figure("paper_simulation", figure)
        writer.close()
    plt.close(figure)

    print(
        f"\n{points} N0 points x {args.trials} trials, scores {list(result.rates)}: {wall:.1f} s wall "
        f"({wall / points * 1e3:.0f} ms per point; {args.workers} worker(s) x {args.threads} thread(s), "
        f"torch {torch.__version__}, {args.dtype})\n"
    )
    timing = [[score, f"{seconds:.1f}", f"{seconds / points * 1e3:.1f}"] for score, seconds in result.seconds.items()]
    print(markdown_table(["score", "seconds (summed over workers)", "ms per N0 point"], timing))
    print()
    header = ["comparison", "largest deviation", "at N0", "ours", "paper", "summary", "criterion"]
    print(markdown_table(header, deviation_rows(result, paper)))
    print(f"\nwrote {output_dir / 'paper_simulation.csv'} and {output_dir / 'paper_simulation.png'}")


if __name__ == "__main__":
    main()
