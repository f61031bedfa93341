r"""Pairs for ``train/fit_mask.py`` whose captured image is a changed scene plus sensor noise (the main job).

Each pair is a 64 x 64 prior section of a map and the captured image of the same ground (co-registered, the yardstick's
size): a scene change of a real photograph (``controlled``: the changes of :mod:`enmi_torch.data.scene_change`, all
kinds mixed, strength drawn in ``--strength``, made on the 88 x 88 window around the section as the yardstick makes
them) or a real pair of another date or modality (``real:<case>/<dataset>`` from ``--data``, a random crop), plus
Gaussian noise of the sensor's per-pixel variance (``yardstick.py``'s profiles, mean sigma ``--level``). The places are
held out from ``data_tools.experiments.yardstick.scene_change``'s trials: the photographs are not the yardstick's maps
(:data:`PHOTOGRAPHS`), and real pairs come from the ``--real-folders`` half of each dataset (``even`` by default; run
the yardstick with ``--real-folders odd``). ``meta.json`` names the sensor's variance map as the truth (the dashboards'
analytic map) and lists the settings and the real folders drawn from.

    python -m data_tools.experiments.mask.scene_change_pairs runs/pairs_controlled --sources controlled --level 60
    python train/fit_mask.py --data.root runs/pairs_controlled --data.batch_size 64 --trainer.max_epochs 10
    python -m data_tools.experiments.yardstick.scene_change --levels 60 --sensors camera-like --real-folders odd \
        --learned-mask runs/fit_mask/version_0/mask/variance_mask.npy --methods "ECR learned" "ECR true" ...
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import numpy as np
import torch
from skimage import color, data

from data_tools.experiments.yardstick import scene_change as scene_change_yardstick
from enmi_torch.data.pairs import write_pairs
from enmi_torch.data.scene_change import CHANGES, scene_change
from enmi_torch.data.truth import VarianceTruth

# scikit-image's bundled photographs other than the yardstick's maps (gravel, brick, camera, astronaut, coffee, rocket).
PHOTOGRAPHS = ("grass", "chelsea", "coins", "moon", "retina", "immunohistochemistry")


YARDSTICK = scene_change_yardstick  # real pairs, folder halves, the sensors' profiles
LOCAL, SPAN = YARDSTICK.LOCAL, YARDSTICK.SPAN


@functools.cache
def photograph(name: str) -> torch.Tensor:
    """Grey ``(H, W)`` float64 in [0, 255] of one of :data:`PHOTOGRAPHS`."""
    image = getattr(data, name)()
    if image.ndim == 3:
        image = color.rgb2gray(image[..., :3]) * 255
    return torch.from_numpy(image.astype(np.float64))


def make_pairs(
    sources: list[str],
    count: int,
    sensor: str,
    level: float,
    strength: tuple[float, float],
    seed: int,
    data_root: Path | None,
    half: str,
):
    """``count`` pairs (dicts of ``local``, ``prior``, ``valid``, ``(LOCAL, LOCAL)``), the truth, the folders used."""
    generator = torch.Generator().manual_seed(seed)
    unit, valid = YARDSTICK.NOISE_ONLY.variance_profile(sensor)
    variance = level**2 * unit
    pools, used = {}, {}
    for source in sources:
        if source == "controlled":
            pools[source] = [(image, image) for image in map(photograph, PHOTOGRAPHS)]
        else:
            name = source.removeprefix("real:")
            pools[source] = [
                (torch.from_numpy(reference), torch.from_numpy(captured))
                for reference, captured in YARDSTICK.real_pairs(data_root, name, half, size=LOCAL)
            ]
            used[source] = [str(folder) for folder in YARDSTICK.pair_folders(data_root, name, half)]
    pairs = []
    for index in range(count):
        source = sources[int(torch.randint(len(sources), (), generator=generator))]
        reference, captured = pools[source][int(torch.randint(len(pools[source]), (), generator=generator))]
        if source == "controlled":
            # The change is made on the window around the section, as the yardstick makes it.
            top = int(torch.randint(reference.shape[0] - SPAN + 1, (), generator=generator))
            left = int(torch.randint(reference.shape[1] - SPAN + 1, (), generator=generator))
            window = reference[top : top + SPAN, left : left + SPAN]
            low, high = strength
            amount = low + (high - low) * float(torch.rand((), generator=generator))
            changed = scene_change(window, seed * 100003 + index, amount, kinds=tuple(CHANGES))
            margin = (SPAN - LOCAL) // 2
            prior = window[margin : margin + LOCAL, margin : margin + LOCAL]
            scene = changed[margin : margin + LOCAL, margin : margin + LOCAL]
        else:
            top = int(torch.randint(reference.shape[0] - LOCAL + 1, (), generator=generator))
            left = int(torch.randint(reference.shape[1] - LOCAL + 1, (), generator=generator))
            prior = reference[top : top + LOCAL, left : left + LOCAL]
            scene = captured[top : top + LOCAL, left : left + LOCAL]
        noise = torch.randn(LOCAL, LOCAL, generator=generator, dtype=torch.float64) * variance.sqrt()
        local = torch.where(valid, scene + noise, 0.0)
        pairs.append({"local": local.float(), "prior": prior.float(), "valid": valid})
    truth = VarianceTruth(torch.where(valid, variance, torch.nan), valid, sensor)
    return pairs, truth, used


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("output", type=Path, help="a new (or empty) folder for the pairs")
    parser.add_argument("--pairs", type=int, default=2000, help="pairs to write (default 2000)")
    parser.add_argument(
        "--sources",
        nargs="+",
        default=["controlled"],
        help="'controlled' and/or real cases 'real:<case>/<dataset>' (one drawn per pair, uniformly)",
    )
    parser.add_argument("--sensor", choices=YARDSTICK.SENSORS, default="camera-like")
    parser.add_argument("--level", type=float, default=60.0, help="mean noise sigma over the valid pixels (60)")
    parser.add_argument("--strength", type=float, nargs=2, default=[0.25, 1.0], help="controlled changes' strengths")
    parser.add_argument("--data", type=Path, default=Path("/work/data/scene_change"), help="real pairs' folder")
    parser.add_argument("--real-folders", choices=("even", "odd", "all"), default="even", help="half of each dataset")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    low, high = args.strength
    if args.pairs < 1 or not args.level > 0 or not 0 < low <= high <= 1:
        parser.error(f"--pairs >= 1, --level > 0 and 0 < --strength low <= high <= 1, got {args}")
    for source in args.sources:
        if source != "controlled" and not source.startswith("real:"):
            parser.error(f"--sources: 'controlled' or 'real:<case>/<dataset>', got {source!r}")
    if args.output.exists() and any(args.output.iterdir()):
        parser.error(f"output must be a new or empty folder, got {str(args.output)!r} which holds files")
    try:
        pairs, truth, used = make_pairs(
            args.sources, args.pairs, args.sensor, args.level, (low, high), args.seed, args.data, args.real_folders
        )
    except ValueError as error:
        parser.error(str(error))
    settings = {key: str(value) if isinstance(value, Path) else value for key, value in vars(args).items()}
    source = json.dumps(
        {"made_by": "data_tools.experiments.mask.scene_change_pairs", **settings, "real_folders_used": used}
    )
    count = write_pairs(args.output, pairs, truth=truth, source=source)
    print(f"wrote {count} pairs of {LOCAL} x {LOCAL} to {args.output} ({', '.join(args.sources)})", file=sys.stderr)


if __name__ == "__main__":
    main()
