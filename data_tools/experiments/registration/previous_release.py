r"""The sub-cell trials of :mod:`data_tools.experiments.registration.subcell` through another checkout's enmi_torch.

``localize`` (``center``, its former spelling) and ``localize(refine=True)`` of the checkout named by
``--checkout`` (its ``enmi_torch`` imported from there) on the same trials as ``subcell`` makes: the parabola's and the
refinement's RMS position error over the trials the search found, and their paired difference with its standard
error. For the previous release, check it out beside the clone first.

    git worktree add /tmp/previous 44b3617   # the release before issue 42
    python -m data_tools.experiments.registration.previous_release --checkout /tmp/previous \
        --photos '/work/data/src/dataset/Optical-Optical/*_1.jpg'
"""

from __future__ import annotations

import argparse
import importlib
import math
import sys
from pathlib import Path

LEVELS = (10.0, 30.0, 90.0)
SENSORS = ("camera-like", "lidar-like")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="example:\n" + __doc__.rsplit("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--checkout", required=True, help="a checkout of enmi_torch (the folder holding enmi_torch/)")
    parser.add_argument("--photos", nargs="+", required=True, help="folders of photographs, or glob patterns")
    parser.add_argument("--trials", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not (Path(args.checkout) / "enmi_torch" / "__init__.py").is_file():
        parser.error(f"--checkout must hold enmi_torch/__init__.py, got {args.checkout!r}")
    from data_tools.experiments.registration import subcell  # the trials, made as the benchmark makes them

    paths = subcell.photo_paths(args.photos)
    if not paths:
        parser.error(f"--photos names no PNG, JPEG or TIFF file: {args.photos}")
    maps, clean, truth, draws = subcell.make_trials(paths, args.trials, args.seed)
    cells = {(sensor, level): subcell.noisy(clean, draws, sensor, level) for sensor in SENSORS for level in LEVELS}
    for name in [name for name in sys.modules if name == "enmi_torch" or name.startswith("enmi_torch.")]:
        del sys.modules[name]  # the checkout's enmi_torch from here on
    sys.path.insert(0, str(Path(args.checkout).resolve()))
    torch = importlib.import_module("torch")
    previous = importlib.import_module("enmi_torch")
    torch.set_num_threads(1)
    print(f"enmi_torch from {Path(previous.__file__).parent}; {args.trials} trials per cell; errors in cells")
    print("| sensor | level | found | parabola | localize(refine=True) (paired - parabola) |")
    print("| --- | --- | --- | --- | --- |")
    centre = subcell.MAP // 2
    offset = torch.tensor([centre, centre, 0.0], dtype=torch.float64)
    for (sensor, level), (captured, variance) in cells.items():
        options = {"shifts": subcell.SHIFTS, "center": (centre, centre)}
        found = previous.localize(captured.float(), maps.float(), variance.float(), **options)
        refined = previous.localize(captured.float(), maps.float(), variance.float(), refine=True, **options)
        start, end = (result.pose.double() + offset for result in (found, refined))
        inside = (start[:, :2] - truth[:, :2]).abs().amax(1) <= 1
        before, after = ((pose[:, :2] - truth[:, :2]).square().sum(1)[inside] for pose in (start, end))
        difference = after - before
        error = float(difference.std()) / math.sqrt(len(difference))
        print(
            f"| {sensor} | {level:g} | {int(inside.sum())} | {math.sqrt(float(before.mean())):.3f} | "
            f"{math.sqrt(float(after.mean())):.3f} ({float(difference.mean()):+.4f} ± {error:.4f}) |",
            flush=True,
        )


if __name__ == "__main__":
    sys.exit(main())
