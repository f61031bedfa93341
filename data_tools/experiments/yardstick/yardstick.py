"""When does the per-pixel variance pay? Localization success of each score against its controls, paired trials.

Each trial cuts a 64 x 64 local image from a map at a known shift (within +-12 cells of the prior position, yaw 0),
passes it through a sensor response, adds Gaussian noise with a per-pixel variance profile, and searches the
25 x 25 shifts of the window with every method on the same noisy image (common random numbers: the same poses and
the same standard-normal draws, scaled, at every noise level). Success: the best shift within one cell of the truth
on both axes.

Maps: scikit-image's CC0 ``gravel`` with painted lane markings, ``brick`` (repetitive), and the photographs
``camera``, ``astronaut``, ``coffee`` and ``rocket`` (grey). Variance profiles, scaled so the mean noise standard
deviation over the valid pixels is the level in grey levels:

* ``camera-like``: 1 on the near (bottom) row to 100 on the far (top) row, growing as depth cubed;
* ``lidar-like``: 1 at the centre to 100 in the corners, growing with the squared range;
* ``paper-camera``: the paper's road camera, analytic (``camera_truth``, ``sigma^2 = N0 / A~``; cells the camera
  does not see are left out).

Responses: ``identity``, and ``nonmonotonic`` (``255 |2 v / 255 - 1|^0.8``: mid-grey bright, dark and white both
dark), where correlation fails and the information scores are needed.

Methods (32 bins for the binned scores):

* ECR (the noise-aware correlation ratio, :func:`enmi_torch.ecr`) with the true per-pixel variance, with a learned
  mask (the paper's empirical variance, :func:`enmi_torch.empirical_variance`, over 1000 aligned pairs), and with
  one uniform variance equal to the true map's mean (ablation);
* ENMI (the paper's, mass weights) with the true variance and with the learned mask;
* the other noise-aware scores, with the true variance: the mixture-likelihood score
  (:func:`enmi_torch.mixture_surface`: the ECR surface picks the peaks, rescored exactly), ENMI with truncated
  likelihood weights (``kernel="truncated"``) and with reliability-weighted counts (``reliability=True``);
* controls: ENMI with one uniform variance equal to the map's mean; ENMI with the *best* uniform variance of the grid
  mean x {1/16, 1/4, 1, 4, 16} picked per cell after the fact (an oracle no user has); hard NMI; NCC.

Prints one table per response and profile (success rate and its standard error), the paired differences that decide
the claims, and where failures put their peak (share on the window's edge), and writes a CSV; ``--figure PATH`` also
draws success against noise, averaged over the maps. Nothing tracked is written unless a path points into the
repository.

    # ~30 min on 2 cores
    python -m data_tools.experiments.yardstick.yardstick --trials 100 --jobs 2 --output /tmp/yardstick
    # a minute
    python -m data_tools.experiments.yardstick.yardstick --trials 8 --maps camera --levels 120 --output /tmp/quick
    python -m data_tools.experiments.yardstick.yardstick --report --output data_tools/results/yardstick \
        --figure docs/images/yardstick.png                                            # the committed tables and figure
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch
from skimage import color, data

from enmi_torch.data.truth import camera_truth
from enmi_torch.geometry.camera import RoadCamera
from enmi_torch.scores import ECR, ENMI, NCC, NMI, Mixture
from enmi_torch.variance import empirical_variance

LOCAL = 64
RADIUS = 12
BINS = 32
PAIRS = 1000
MAPS = ("gravel", "brick", "camera", "astronaut", "coffee", "rocket")
PROFILES = ("camera-like", "lidar-like", "paper-camera")
RESPONSES = ("identity", "nonmonotonic")
LEVELS = (40.0, 120.0, 240.0, 480.0)
GRID = (1 / 16, 1 / 4, 1.0, 4.0, 16.0)
METHODS = (
    "ECR true",
    "ECR learned",
    "ECR uniform mean",
    "ECR linear true",
    "Mixture true",
    "ENMI truncated true",
    "ENMI reliability true",
    "ENMI true",
    "ENMI learned",
    "ENMI uniform mean",
    "ENMI best uniform",
    "NMI",
    "NCC",
)


# The score and the variance ("true", "learned", "mean" or none) of each method but the uniform-grid controls.
METHOD_SCORES = {
    "ECR true": (ECR(bins=BINS), "true"),
    "ECR learned": (ECR(bins=BINS), "learned"),
    "ECR uniform mean": (ECR(bins=BINS), "mean"),
    "ECR linear true": (ECR(bins=BINS, response="linear"), "true"),
    "Mixture true": (Mixture(bins=BINS), "true"),
    "ENMI truncated true": (ENMI(bins=BINS, kernel="truncated"), "true"),
    "ENMI reliability true": (ENMI(bins=BINS, reliability=True), "true"),
    "ENMI true": (ENMI(bins=BINS), "true"),
    "ENMI learned": (ENMI(bins=BINS), "learned"),
    "NMI": (NMI(bins=BINS), None),
    "NCC": (NCC(), None),
}
# The uniform-variance controls: this score at the mean variance times each factor of GRID.
GRID_SCORE = ENMI(bins=BINS)


def map_image(name: str) -> torch.Tensor:
    """Grey-level map ``(H, W)`` float64 in [0, 255]."""
    if name == "gravel":
        image = data.gravel().astype(np.float64)
        paint = 232.0
        image[:, 96:102] = paint  # solid edge lines
        image[:, 410:416] = paint
        for start in range(0, 512, 48):  # dashed centre line
            image[start : start + 24, 253:259] = paint
        image[300:308, 102:253] = paint  # stop bar
    else:
        image = getattr(data, name)()
        if image.ndim == 3:
            image = color.rgb2gray(image[..., :3]) * 255
        image = image.astype(np.float64)
    return torch.from_numpy(image)


def variance_profile(name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit variance profile ``(LOCAL, LOCAL)`` (mean standard deviation 1 over the valid cells) and valid cells."""
    rows = torch.arange(LOCAL, dtype=torch.float64)
    valid = torch.ones(LOCAL, LOCAL, dtype=torch.bool)
    if name == "camera-like":
        depth = 1 + (100 ** (1 / 3) - 1) * (LOCAL - 1 - rows) / (LOCAL - 1)  # far row 0
        profile = (depth**3)[:, None].expand(LOCAL, LOCAL).clone()
    elif name == "lidar-like":
        centre = (LOCAL - 1) / 2
        squared_range = ((rows - centre)[:, None] ** 2 + (rows - centre)[None] ** 2) / (2 * centre**2)
        profile = 1 + 99 * squared_range
    else:
        truth = camera_truth((LOCAL, LOCAL), 1.0, distance_range=RoadCamera.paper().visible_distance_range())
        valid = truth.valid
        profile = torch.where(valid, truth.variance, 1.0)
    profile = profile / profile[valid].sqrt().mean() ** 2
    return torch.where(valid, profile, 1.0), valid


def respond(values: torch.Tensor, response: str) -> torch.Tensor:
    return values if response == "identity" else 255 * (2 * values / 255 - 1).abs() ** 0.8


def _crops(image, tops, lefts, size):
    return torch.stack([image[top : top + size, left : left + size] for top, left in zip(tops, lefts, strict=True)])


def run_cell(
    map_name: str,
    profile: str,
    response: str,
    levels: tuple[float, ...],
    trials: int,
    seed: int,
    pairs: int = PAIRS,
    methods: tuple[str, ...] = METHODS,
) -> list:
    """Rows ``(map, profile, response, level, method, successes, trials, edge_failures, outcomes)`` for one cell."""
    torch.set_num_threads(1)
    generator = torch.Generator().manual_seed(seed)
    image = map_image(map_name)
    unit, valid = variance_profile(profile)
    height, width = image.shape
    span = LOCAL + 2 * RADIUS
    tops = torch.randint(0, height - span + 1, (trials,), generator=generator).tolist()
    lefts = torch.randint(0, width - span + 1, (trials,), generator=generator).tolist()
    shifts = torch.randint(-RADIUS + 1, RADIUS, (trials, 2), generator=generator)
    windows = _crops(image, tops, lefts, span)[:, None]
    clean = respond(
        torch.stack(
            [
                window[0, RADIUS + dy : RADIUS + dy + LOCAL, RADIUS + dx : RADIUS + dx + LOCAL]
                for window, (dy, dx) in zip(windows, shifts.tolist(), strict=True)
            ]
        )[:, None],
        response,
    )
    draws = torch.randn(clean.shape, generator=generator, dtype=torch.float64)
    # Pairs for the learned mask: aligned crops elsewhere in the map, their own noise.
    pair_tops = torch.randint(0, height - LOCAL + 1, (pairs,), generator=generator).tolist()
    pair_lefts = torch.randint(0, width - LOCAL + 1, (pairs,), generator=generator).tolist()
    pair_clean = respond(_crops(image, pair_tops, pair_lefts, LOCAL)[:, None], response)
    pair_draws = torch.randn(pair_clean.shape, generator=generator, dtype=torch.float64)
    truth = shifts + RADIUS
    rows = []
    for level in levels:
        variance = (level**2 * unit)[None, None]
        local = (clean + draws * variance.sqrt()).where(valid, 0.0).float()
        learned, observed = empirical_variance(pair_clean + pair_draws * variance.sqrt(), pair_clean, valid[None, None])
        learned = torch.where(observed, learned, 1.0).reshape(1, 1, LOCAL, LOCAL).float()
        mask = (valid & observed.reshape(LOCAL, LOCAL))[None, None]
        mean = float(variance[0, 0][valid].mean())
        true_variance = variance.float()
        window = windows.float()
        variances = {"true": true_variance, "learned": learned, "mean": mean, None: None}
        searches = _searches(local, window, variances, mask)
        outcomes = {
            method: _outcomes(search().score, truth) for method, search in searches.items() if method in methods
        }
        best = 1.0
        if {"ENMI uniform mean", "ENMI best uniform"} & set(methods):
            grid = {
                factor: _outcomes(GRID_SCORE.surface(local, window, mean * factor, captured_mask=mask).score, truth)
                for factor in GRID
            }
            best = max(GRID, key=lambda factor: (int(grid[factor][0].sum()), factor == 1.0))
            outcomes["ENMI uniform mean"], outcomes["ENMI best uniform"] = grid[1.0], grid[best]
        for method in methods:
            success, edge = outcomes[method]
            label = f"{method} (x{best:g})" if method == "ENMI best uniform" else method
            bits = "".join("1" if value else "0" for value in success.tolist())
            rows.append((map_name, profile, response, level, label, int(success.sum()), trials, int(edge.sum()), bits))
    return rows


def _searches(local, window, variances, mask) -> dict:
    """Each method's surface, computed when called."""

    def search(score, kind):
        return lambda: score.surface(local, window, variances[kind], captured_mask=mask)

    return {method: search(score, kind) for method, (score, kind) in METHOD_SCORES.items()}


def _outcomes(score: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per trial: success (peak within one cell of the truth) and failure with the peak on the window's edge."""
    columns = score.shape[-1]
    peak = score.flatten(1).argmax(1)
    peak_rows, peak_cols = peak // columns, peak % columns
    success = ((peak_rows - truth[:, 0]).abs() <= 1) & ((peak_cols - truth[:, 1]).abs() <= 1)
    on_edge = (peak_rows == 0) | (peak_cols == 0) | (peak_rows == score.shape[-2] - 1) | (peak_cols == columns - 1)
    return success, ~success & on_edge


def cells(args) -> list[tuple[str, str, str]]:
    chosen = []
    for response in args.responses:
        for profile in args.profiles:
            for map_name in args.maps:
                chosen.append((map_name, profile, response))
    return chosen


def _method(label: str) -> str:
    return label.split(" (x")[0]


def methods_in(table) -> list[str]:
    """The methods of :data:`METHODS` that the result rows hold (older CSVs may lack some)."""
    present = {key[4] for key in table}
    return [method for method in METHODS if method in present]


def report(rows: list, figure: Path | None = None) -> None:
    """Tables and paired claims from the result rows; the figure too where ``figure`` names its PNG."""
    table = {}
    for map_name, profile, response, level, label, successes, trials, edge, bits in rows:
        table[map_name, profile, response, level, _method(label)] = (label, successes, trials, edge, bits)
    keys = sorted({key[:4] for key in table}, key=lambda key: (RESPONSES.index(key[2]), PROFILES.index(key[1])))
    groups = {}
    for key in keys:
        groups.setdefault(key[2:0:-1], []).append(key)
    for (response, profile), group in groups.items():
        print(f"\n### {response} response, {profile} variance: success rate ± SE ({_trials(table, group[0])} trials)\n")
        print("| map | mean sigma | " + " | ".join(methods_in(table)) + " |")
        print("|---|---|" + "---|" * len(methods_in(table)))
        for key in sorted(group, key=lambda key: (MAPS.index(key[0]), key[3])):
            cells_text = []
            for method in methods_in(table):
                label, successes, trials, _, _ = table[(*key, method)]
                rate = successes / trials
                text = f"{rate:.2f} ± {math.sqrt(rate * (1 - rate) / trials):.2f}"
                if method == "ENMI best uniform":
                    text += label[len(method) :]
                cells_text.append(text)
            print(f"| {key[0]} | {key[3]:g} | " + " | ".join(cells_text) + " |")
    _print_summary(table, keys)
    _print_claims(table, keys)
    _print_edges(table, keys)
    if figure is not None:
        _plot(table, keys, figure)
        print(f"\nwrote {figure}")


def _print_summary(table, keys) -> None:
    """Success rate averaged over the maps, per response, profile and noise level (the README table)."""
    print(f"\n### Mean success rate over the maps (each map: {_trials(table, keys[0])} paired trials)\n")
    print("| response | variance | mean sigma | " + " | ".join(methods_in(table)) + " |")
    print("|---|---|---|" + "---|" * len(methods_in(table)))
    groups = sorted({key[1:] for key in keys}, key=lambda g: (RESPONSES.index(g[1]), PROFILES.index(g[0]), g[2]))
    for profile, response, level in groups:
        group = [key for key in keys if key[1:] == (profile, response, level)]
        rates = [
            np.mean([table[(*key, method)][1] / table[(*key, method)][2] for key in group])
            for method in methods_in(table)
        ]
        best = max(rates)
        cells = [f"**{rate:.2f}**" if rate == best else f"{rate:.2f}" for rate in rates]
        print(f"| {response} | {profile} | {level:g} | " + " | ".join(cells) + " |")


def _trials(table, key) -> int:
    return table[(*key, methods_in(table)[0])][2]


def _paired(table, key, first: str, second: str) -> tuple[float, float]:
    """Mean difference of success (first - second) over the paired trials and its standard error."""
    a = np.array([int(bit) for bit in table[(*key, first)][4]])
    b = np.array([int(bit) for bit in table[(*key, second)][4]])
    difference = a - b
    return float(difference.mean()), float(difference.std(ddof=1) / math.sqrt(len(difference))) if len(a) > 1 else 0.0


def _print_claims(table, keys) -> None:
    present = set(methods_in(table))
    print("\n### Paired differences of ECR (true variance) against each control: cells where it is > 1 SE below\n")
    controls = ("ENMI best uniform", "ENMI uniform mean", "NMI", "NCC", "ECR uniform mean")
    below = {control: [] for control in controls if control in present}
    for key in keys:
        for control in below:
            mean, error = _paired(table, key, "ECR true", control)
            if mean < -error - 1e-12:
                below[control].append(f"{key[0]}/{key[1]}/{key[2]}/{key[3]:g}: {mean:+.2f} ± {error:.2f}")
    for control, failures in below.items():
        print(
            f"- vs {control}: {len(keys) - len(failures)}/{len(keys)} cells within 1 SE or above"
            + ("; below in " + "; ".join(failures) if failures else "")
        )
    if {"ECR linear true", "NCC"} <= present:
        identity = [key for key in keys if key[2] == "identity"]
        failures = []
        for key in identity:
            mean, error = _paired(table, key, "ECR linear true", "NCC")
            if mean < -error - 1e-12:
                failures.append(f"{key[0]}/{key[1]}/{key[3]:g}: {mean:+.2f} ± {error:.2f}")
        print(
            f"- ECR with the linear response vs NCC, identity response: {len(identity) - len(failures)}/"
            f"{len(identity)} cells within 1 SE or above" + ("; below in " + "; ".join(failures) if failures else "")
        )
    if "ENMI uniform mean" in present:
        print("\n### ECR true minus ENMI uniform mean, camera-like variance, two highest levels (need >= 2 SE)\n")
        levels = sorted({key[3] for key in keys})
        for key in keys:
            if key[1] == "camera-like" and key[3] in levels[-2:]:
                mean, error = _paired(table, key, "ECR true", "ENMI uniform mean")
                verdict = "yes" if mean >= 2 * error and mean > 0 else "no"
                print(
                    f"- {key[0]}, {key[2]}, sigma {key[3]:g}: {mean:+.2f} ± {error:.2f} "
                    f"({mean / max(error, 1e-12):.1f} SE): {verdict}"
                )
    print("\n### Non-monotonic response: is ECR (true variance) the best of the other scores (within 1 SE)?\n")
    for key in keys:
        if key[2] == "nonmonotonic":
            rates = {method: table[(*key, method)][1] for method in present if not method.startswith("ECR ")}
            rates["ECR true"] = table[(*key, "ECR true")][1]
            winner = max(rates, key=rates.get)
            mean, error = _paired(table, key, "ECR true", winner)
            verdict = "yes" if winner == "ECR true" or mean >= -error else "no"
            print(
                f"- {key[0]}, {key[1]}, sigma {key[3]:g}: best {winner} ({rates[winner]}); "
                f"ECR true {mean:+.2f} ± {error:.2f}: {verdict}"
            )
    if "ECR learned" in present:
        print("\n### ECR learned mask minus ECR true variance: cells > 1 SE below\n")
        failures = []
        for key in keys:
            mean, error = _paired(table, key, "ECR learned", "ECR true")
            if mean < -error - 1e-12:
                failures.append(f"{key[0]}/{key[1]}/{key[2]}/{key[3]:g}: {mean:+.2f} ± {error:.2f}")
        print(
            f"- {len(keys) - len(failures)}/{len(keys)} cells within 1 SE or above"
            + ("; below in " + "; ".join(failures) if failures else "")
        )


def _print_edges(table, keys) -> None:
    print("\n### Where failures put their peak: share of failures on the window's edge (all cells)\n")
    print("| method | failures | on the edge |")
    print("|---|---|---|")
    for method in methods_in(table):
        failures = sum(table[(*key, method)][2] - table[(*key, method)][1] for key in keys)
        edge = sum(table[(*key, method)][3] for key in keys)
        print(f"| {method} | {failures} | {edge / max(failures, 1):.0%} |")


COLOURS = {
    "ECR true": "#d62728",
    "ECR learned": "#ff9896",
    "ECR uniform mean": "#e377c2",
    "Mixture true": "#9467bd",
    "ECR linear true": "#17becf",
    "ENMI truncated true": "#8c564b",
    "ENMI reliability true": "#c49c94",
    "ENMI true": "#1f77b4",
    "ENMI learned": "#aec7e8",
    "ENMI uniform mean": "#2ca02c",
    "ENMI best uniform": "#98df8a",
    "NMI": "#7f7f7f",
    "NCC": "#ff7f0e",
}


def _plot(table, keys, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    responses = [name for name in RESPONSES if any(key[2] == name for key in keys)]
    profiles = [name for name in PROFILES if any(key[1] == name for key in keys)]
    figure, axes = plt.subplots(
        len(responses), len(profiles), figsize=(4.2 * len(profiles), 3.6 * len(responses)), sharey=True, squeeze=False
    )
    styles = {
        "ECR true": "o-",
        "ECR learned": "s--",
        "ENMI true": "v-",
        "ENMI uniform mean": "^-",
        "ENMI best uniform": "D:",
        "NMI": "x-",
        "NCC": "+-",
        "ECR uniform mean": ".:",
        "ENMI learned": "<--",
        "Mixture true": "*-",
        "ECR linear true": "h-",
        "ENMI truncated true": "1-",
        "ENMI reliability true": "2-",
    }
    for row, response in enumerate(responses):
        for col, profile in enumerate(profiles):
            axis = axes[row, col]
            levels = sorted({key[3] for key in keys if key[1:3] == (profile, response)})
            for method in methods_in(table):
                rates = []
                for level in levels:
                    group = [key for key in keys if key[1:] == (profile, response, level)]
                    rates.append(np.mean([table[(*key, method)][1] / table[(*key, method)][2] for key in group]))
                axis.plot(levels, rates, styles[method], label=method, color=COLOURS[method])
            axis.set_xscale("log")
            axis.set_xticks(levels, [f"{level:g}" for level in levels])
            axis.minorticks_off()
            axis.set(title=f"{profile} variance, {response}", ylim=(-0.03, 1.03))
            axis.grid(alpha=0.3)
            if row == len(responses) - 1:
                axis.set_xlabel("mean noise sigma (grey levels)")
        axes[row, 0].set_ylabel("success rate (mean over maps)")
    axes[0, 0].legend(fontsize=7, loc="lower left")
    figure.tight_layout()
    figure.savefig(path, dpi=80)
    plt.close(figure)
    print(f"\nwrote {path}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    parser.add_argument("--trials", type=int, default=100, help="paired trials per cell (default 100)")
    parser.add_argument("--maps", nargs="+", choices=MAPS, default=list(MAPS))
    parser.add_argument("--profiles", nargs="+", choices=PROFILES, default=list(PROFILES))
    parser.add_argument("--responses", nargs="+", choices=RESPONSES, default=list(RESPONSES))
    parser.add_argument("--levels", nargs="+", type=float, default=list(LEVELS), help="mean noise sigmas")
    parser.add_argument("--pairs", type=int, default=PAIRS, help=f"aligned pairs behind the learned mask ({PAIRS})")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (one torch thread each)")
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS), help="a subset of the methods")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=Path("/tmp/enmi_yardstick"), help="CSV path (stem)")
    parser.add_argument("--figure", type=Path, help="draw success against noise into this PNG")
    parser.add_argument("--report", action="store_true", help="only print the tables of an existing --output CSV")
    args = parser.parse_args(argv)
    if args.trials < 2 or args.jobs < 1 or args.pairs < 2:
        parser.error(f"--trials and --pairs must be >= 2 and --jobs >= 1, got {args.trials}, {args.pairs}, {args.jobs}")
    output = args.output.with_suffix(".csv")
    if args.report:
        if not output.exists():
            parser.error(f"--output: {output} does not exist; run without --report first")
        with output.open() as file:
            rows = [
                (*row[:3], float(row[3]), row[4], int(row[5]), int(row[6]), int(row[7]), row[8])
                for row in list(csv.reader(file))[1:]
            ]
        report(rows, args.figure)
        return
    output.parent.mkdir(parents=True, exist_ok=True)
    chosen = cells(args)
    start = time.perf_counter()
    rows = []
    with ProcessPoolExecutor(args.jobs) as pool:
        futures = [
            pool.submit(
                run_cell,
                map_name,
                profile,
                response,
                tuple(args.levels),
                args.trials,
                args.seed * 1000
                + MAPS.index(map_name) * 100
                + PROFILES.index(profile) * 10
                + RESPONSES.index(response),
                args.pairs,
                tuple(args.methods),
            )
            for map_name, profile, response in chosen
        ]
        for done, future in enumerate(futures, 1):
            rows += future.result()
            print(
                f"[{done}/{len(futures)}] {' '.join(chosen[done - 1])} done, {time.perf_counter() - start:.0f} s",
                file=sys.stderr,
                flush=True,
            )
    with output.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(
            ["map", "profile", "response", "mean_sigma", "method", "successes", "trials", "edge_failures", "outcomes"]
        )
        writer.writerows(rows)
    print(
        f"{len(chosen)} cells x {len(args.levels)} levels x {args.trials} trials "
        f"in {time.perf_counter() - start:.0f} s "
        f"(one torch thread per job, {args.jobs} jobs); wrote {output}"
    )
    report(rows, args.figure)


if __name__ == "__main__":
    main()
