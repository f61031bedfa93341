"""Success rate of map localization against noise power N0: ECR and ENMI (analytic and learned variance), NMI, NCC.

Prior maps are scikit-image's bundled CC0 textures: ``gravel()`` with painted lane markings (solid and dashed lines,
a stop bar) and ``brick()``, a repetitive, ambiguous pattern. Each trial cuts a local image at a known pose (an
integer shift within the search window and a yaw on the searched grid) around a random prior position, rotated
with kornia, and adds Gaussian noise of per-cell variance given by one of two sensor models:

* ``camera``: the rectified bird's-eye view of the paper's road camera (``RoadCamera.paper()``), from
  :func:`enmi_torch.data.truth.camera_truth`: a :class:`~enmi_torch.geometry.rectify.GroundGrid` of 2.5 cm cells from
  200 cm (row 0) to 40 cm ahead (the camera's visible distance range), columns lateral, with the analytic variance
  sigma^2 = N0 / A~ of :func:`enmi_torch.variance.perspective_variance` (A~ the focal-plane area of each cell's
  visible part, paper eq. TildeA: far cells are noisy); cells whose centre the camera does not see
  (:func:`enmi_torch.geometry.rectify.visible_cells`) are invalid.
* ``lidar``: :func:`enmi_torch.data.truth.lidar_truth`, sigma^2 = N0 (1 + 3 (r / R)^2) growing with the range r from
  the vehicle at the image centre; cells beyond R (half the image) are out of range and invalid.

The local image is then searched by :func:`enmi_torch.localize` (shifts within +-8 cells, yaws -4..4 by
2 degrees) with ECR (the noise-aware correlation ratio, the library's default) and with the paper's ENMI, each with:

* the analytic variance: the true variance map of the sensor model;
* the learned mask: the paper's empirical mask (section "Ford Image Analysis"),
  Var[i, j] = 1 / (n - 1) sum_k (a_ij - a~_ij)^2, computed by :func:`enmi_torch.variance.empirical_variance` over
  ``--pairs`` synthetic aligned pairs at random poses (noisy local image against its noiseless rendering, so the
  residuals are the sensor noise); cells it never observed are invalid;
* NMI (hard bins) and NCC, on the same valid cells.

With ``--response nonmonotonic`` the local sensor sees the ground through a non-monotonic grey-level response
(``255 |2 v / 255 - 1|^0.8``: mid-grey road bright, dark gravel and white paint both dark), as when a camera image is
matched against a map made by another sensor: the case mutual information is for, and where correlation fails.

Success: |dx|, |dy| errors <= 1 cell and yaw error <= 1 degree. Prints one table per map and sensor model;
``--figure PATH`` also draws success against noise into PATH.

    python -m data_tools.experiments.yardstick.localization_benchmark  # 26 s (quiet) to 150 s (busy) on a 2-core CPU
    python -m data_tools.experiments.yardstick.localization_benchmark --response nonmonotonic
    python -m data_tools.experiments.yardstick.localization_benchmark --trials 100    # tighter rates
    python -m data_tools.experiments.yardstick.localization_benchmark --figure docs/images/localization_success.png
    # files for the command line tool
    python -m data_tools.experiments.yardstick.localization_benchmark --example runs/example
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.transform import rotate
from skimage import data
from tqdm import tqdm

from enmi_torch.data.truth import camera_truth, lidar_truth
from enmi_torch.geometry.camera import RoadCamera
from enmi_torch.localization.search import localize
from enmi_torch.scores import ECR, ENMI, NCC, NMI
from enmi_torch.variance import empirical_variance

LOCAL = 64
RADIUS = 8
YAWS = [-4.0, -2.0, 0.0, 2.0, 4.0]
NOISE_POWERS = {"camera": [1e-4, 1e-3, 3e-3, 1e-2, 3e-2], "lidar": [200.0, 1800.0, 5400.0, 16200.0, 48600.0]}
METHODS = (
    "ECR, analytic variance",
    "ECR, learned mask",
    "ENMI, analytic variance",
    "ENMI, learned mask",
    "NMI",
    "NCC",
)


def prior_map(name: str) -> torch.Tensor:
    """``gravel`` with painted markings or ``brick``, ``(1, 1, 512, 512)`` float64 grey levels."""
    if name == "brick":
        image = data.brick().astype(np.float64)
    else:
        image = data.gravel().astype(np.float64)
        paint = 232.0
        image[:, 96:102] = paint  # solid edge line
        image[:, 410:416] = paint
        for start in range(0, 512, 48):  # dashed centre line: 24 cells painted, 24 not
            image[start : start + 24, 253:259] = paint
        image[300:308, 102:253] = paint  # stop bar across one lane
    return torch.from_numpy(image).reshape(1, 1, 512, 512)


def sensor_model(name: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Variance per unit noise power (1 where invalid) and the valid cells, ``(1, 1, LOCAL, LOCAL)`` each."""
    if name == "lidar":
        truth = lidar_truth((LOCAL, LOCAL), 1.0, 2.0, range_fraction=1.0)
    else:
        truth = camera_truth((LOCAL, LOCAL), 1.0, distance_range=RoadCamera.paper().visible_distance_range())
    unit_variance = torch.where(truth.valid, truth.variance, 1.0)
    return unit_variance.reshape(1, 1, LOCAL, LOCAL), truth.valid.reshape(1, 1, LOCAL, LOCAL)


def cut(prior: torch.Tensor, centers: torch.Tensor, yaws: torch.Tensor) -> torch.Tensor:
    """Local images ``(B, 1, LOCAL, LOCAL)`` whose centre pixel lies on ``centers`` (row, col), rotated by ``yaws``."""
    sections = torch.stack(
        [prior[0, :, row - LOCAL : row + LOCAL, col - LOCAL : col + LOCAL] for row, col in centers.tolist()]
    )
    turned = rotate(sections, yaws.to(sections.dtype))
    half = LOCAL // 2
    return turned[..., LOCAL - half : LOCAL - half + LOCAL, LOCAL - half : LOCAL - half + LOCAL]


def random_poses(generator: torch.Generator, count: int, margin: int):
    """Prior centres, true shifts (dy, dx) inside the window (one cell from its edge) and true yaws."""
    priors = torch.randint(margin, 512 - margin, (count, 2), generator=generator)
    shifts = torch.randint(-RADIUS + 1, RADIUS, (count, 2), generator=generator)
    yaws = torch.tensor(YAWS, dtype=torch.float64)[torch.randint(len(YAWS), (count,), generator=generator)]
    return priors, shifts, yaws


def learned_mask(prior, unit_variance, valid, noise_power, pairs, generator, response):
    """The paper's empirical variance from ``pairs`` aligned local/prior pairs (1 where unobserved), and its cells."""
    centers = torch.randint(2 * LOCAL, 512 - 2 * LOCAL, (pairs, 2), generator=generator)
    yaws = (torch.rand(pairs, generator=generator, dtype=torch.float64) - 0.5) * 360
    clean = sensor_response(cut(prior, centers, yaws), response)
    noise = torch.randn(clean.shape, generator=generator, dtype=torch.float64) * (noise_power * unit_variance).sqrt()
    variance, observed = empirical_variance(clean + noise, clean, valid)
    return torch.where(observed, variance, 1.0).reshape(valid.shape), observed.reshape(valid.shape)


def sensor_response(values: torch.Tensor, response: str) -> torch.Tensor:
    """Grey levels the local sensor reports for map grey levels ``values``."""
    if response == "identity":
        return values
    return 255 * (2 * values / 255 - 1).abs() ** 0.8


def run_trials(map_name, model, noise_power, trials, pairs, bins, seed, response="identity"):
    """Successes per method for one map, sensor model and noise power."""
    generator = torch.Generator().manual_seed(seed)
    prior = prior_map(map_name)
    unit_variance, valid = sensor_model(model)
    variance = noise_power * unit_variance
    priors, shifts, yaws = random_poses(generator, trials, LOCAL + RADIUS + 2)
    clean = sensor_response(cut(prior, priors + shifts, yaws), response)
    local = clean + torch.randn(clean.shape, generator=generator, dtype=torch.float64) * variance.sqrt()
    local = torch.where(valid, local, 0.0).float()
    learned, observed = learned_mask(prior, unit_variance, valid, noise_power, pairs, generator, response)
    settings = {"shifts": RADIUS, "around": priors.flip(1), "yaws": YAWS}  # priors are (row, col)
    ecr, enmi = ECR(bins=bins), ENMI(bins=bins)
    searches = {
        METHODS[0]: localize(local, prior.float(), variance.float(), score=ecr, captured_mask=valid, **settings),
        METHODS[1]: localize(local, prior.float(), learned.float(), score=ecr, captured_mask=observed, **settings),
        METHODS[2]: localize(local, prior.float(), variance.float(), score=enmi, captured_mask=valid, **settings),
        METHODS[3]: localize(local, prior.float(), learned.float(), score=enmi, captured_mask=observed, **settings),
        METHODS[4]: localize(local, prior.float(), score=NMI(bins=bins), captured_mask=valid, **settings),
        METHODS[5]: localize(local, prior.float(), score=NCC(), captured_mask=valid, **settings),
    }
    truth = torch.cat([shifts[:, 1:], shifts[:, :1], yaws[:, None]], dim=1)
    successes = {}
    for method, result in searches.items():
        error = (torch.cat([result.shift, result.yaw[:, None]], 1).double() - truth).abs()
        successes[method] = int(((error[:, 0] <= 1) & (error[:, 1] <= 1) & (error[:, 2] <= 1)).sum())
    return successes


EXAMPLE_FILES = ("map.npy", "local.npy", "variance.npy", "local_mask.npy")


def write_example(directory: Path, seed: int, overwrite: bool = False) -> None:
    """A gravel map, a camera-model local image at a known pose and its variance and mask, as .npy files.

    Refuses to replace the files of an earlier call unless ``overwrite``.
    """
    earlier = [name for name in EXAMPLE_FILES if (directory / name).exists()]
    if earlier and not overwrite:
        raise FileExistsError(
            f"--example {str(directory)!r} already holds {', '.join(earlier)}; choose another folder, or pass "
            "--overwrite to replace them"
        )
    directory.mkdir(parents=True, exist_ok=True)
    generator = torch.Generator().manual_seed(seed)
    prior = prior_map("gravel")
    unit_variance, valid = sensor_model("camera")
    variance = 3e-4 * unit_variance
    center, shift, yaw = torch.tensor([[300, 220]]), torch.tensor([[5, -9]]), torch.tensor([3.0], dtype=torch.float64)
    local = cut(prior, center + shift, yaw)
    local = torch.where(
        valid, local + torch.randn(local.shape, generator=generator, dtype=torch.float64) * variance.sqrt(), 0.0
    )
    np.save(directory / "map.npy", prior[0, 0].numpy().astype(np.float32))
    np.save(directory / "local.npy", local[0, 0].numpy().astype(np.float32))
    np.save(directory / "variance.npy", variance[0, 0].numpy().astype(np.float32))
    np.save(directory / "local_mask.npy", valid[0, 0].numpy())
    print(
        f"wrote map.npy, local.npy, variance.npy, local_mask.npy to {directory}: prior pose (x, y) = (220, 300), "
        f"true pose (x, y, yaw) = (211, 305, 3 degrees): dx=-9, dy=5 (camera model, N0 = 3e-4)"
    )


def plot(rates: dict, trials: int, bins: int, response: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(2, 2, figsize=(9.5, 7), sharey=True)
    for row, map_name in enumerate(("gravel", "brick")):
        for col, model in enumerate(("camera", "lidar")):
            axis = axes[row, col]
            powers = NOISE_POWERS[model]
            for method, marker in zip(METHODS, "ovsD^x", strict=True):
                axis.plot(
                    powers, [rates[map_name, model, power][method] for power in powers], marker=marker, label=method
                )
            axis.set_xscale("log")
            axis.set(title=f"{map_name}, {model} noise", xlabel="noise power N0", ylim=(-0.03, 1.03))
            axis.grid(alpha=0.3)
    for axis in axes[:, 0]:
        axis.set_ylabel(f"success rate ({trials} trials)")
    axes[0, 0].legend(fontsize=8, loc="lower left")
    figure.suptitle(
        f"Localization success (|dx|, |dy| <= 1 cell, |yaw| <= 1°): 64 x 64 local, +-8 cells, 5 yaws, {bins} bins, "
        f"{response} response",
        fontsize=10,
    )
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.epilog = "examples:\n" + __doc__.rsplit("\n\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--trials", type=int, default=24, help="trials per map, sensor model and N0")
    parser.add_argument("--pairs", type=int, default=200, help="pairs behind the learned mask")
    parser.add_argument("--bins", type=int, default=16, help="bins of ENMI and NMI (16 suit ~3000 valid cells)")
    parser.add_argument("--response", choices=("identity", "nonmonotonic"), default="identity")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--figure", type=Path, help="draw success against noise into this PNG")
    parser.add_argument("--example", type=Path, help="only write the command-line example files to this folder")
    parser.add_argument("--overwrite", action="store_true", help="let --example replace the files of an earlier call")
    args = parser.parse_args()
    if args.example is not None:
        try:
            write_example(args.example, args.seed, args.overwrite)
        except FileExistsError as error:
            parser.error(str(error))
        return
    start = time.perf_counter()
    rates = {}
    bar = tqdm(total=2 * sum(map(len, NOISE_POWERS.values())), desc="map, sensor, N0", unit="row")
    for map_name in ("gravel", "brick"):
        for model in ("camera", "lidar"):
            tqdm.write(
                f"\n{map_name}, {model} noise, {args.response} response: success rate over {args.trials} trials\n"
            )
            tqdm.write("| N0 | " + " | ".join(METHODS) + " |")
            tqdm.write("|" + " --- |" * (len(METHODS) + 1))
            for index, power in enumerate(NOISE_POWERS[model]):
                seed = args.seed * 1000 + index
                successes = run_trials(map_name, model, power, args.trials, args.pairs, args.bins, seed, args.response)
                rates[map_name, model, power] = {method: count / args.trials for method, count in successes.items()}
                cells = " | ".join(f"{successes[method] / args.trials:.2f}" for method in METHODS)
                tqdm.write(f"| {power:g} | {cells} |")
                bar.update()
    bar.close()
    if args.figure is not None:
        plot(rates, args.trials, args.bins, args.response, args.figure)
        print(f"\nwrote {args.figure}")
    print(f"\n{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
