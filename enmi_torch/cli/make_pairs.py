"""``enmi-make-pairs`` (also ``python -m enmi_torch.cli.make_pairs``): write synthetic local/prior pairs to a folder."""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

from enmi_torch.data import SyntheticPairs, gravel_texture, make_truth, write_pairs
from enmi_torch.utils.command import ArgumentParser, run_command, with_flag_names

PROG = "enmi-make-pairs"
DESCRIPTION = f"""\
Write synthetic local/prior image pairs to a folder in the pair format that enmi-fit-mask --data.root reads: local/,
prior/, valid/ (one file per pair, .npy or 8-bit .png), meta.json and the true variance map truth_variance.npy (NaN
where invalid), which the training dashboards compare the learned mask with. 2,000 pairs of 128x128 take about
300 MB as .npy: write them outside the repository or under its runs/ folder, which git ignores.

examples:
  {PROG} runs/pairs --pairs 2000                 # also: python -m enmi_torch.cli.make_pairs runs/pairs ...
  enmi-fit-mask --data.root runs/pairs"""


# The library's parameter names as this command's flags, for its messages.
FLAGS = {
    "root": "OUT",
    "count": "--pairs",
    "noise_std": "--noise-std",
    "gain_std": "--gain-std",
    "offset_std": "--offset-std",
    "seed": "--seed",
}


def main(argv: Sequence[str] | None = None) -> None:
    """Console entry point: ``enmi-make-pairs --help``."""
    run_command(PROG, make_pairs, argv)


def make_pairs(argv: Sequence[str]) -> None:
    """The command with these arguments."""
    parser = ArgumentParser(prog=PROG, description=DESCRIPTION)
    parser.add_argument("out", metavar="OUT", help="new (or empty) folder to write")
    parser.add_argument("--pairs", type=int, default=2000, help="number of pairs")
    parser.add_argument("--flavour", choices=("lidar", "camera"), default="lidar", help="noise field")
    parser.add_argument("--size", type=int, default=128, help="image side in pixels, at most 512")
    parser.add_argument("--noise-std", type=float, default=12.0, help="RMS noise std over valid pixels")
    parser.add_argument("--gain-std", type=float, default=0.0, help="std of a per-pair intensity gain")
    parser.add_argument("--offset-std", type=float, default=0.0, help="std of a per-pair intensity offset")
    parser.add_argument("--format", choices=("npy", "png"), default="npy", help="image files")
    parser.add_argument("--seed", type=int, default=0, help="pairs are a function of (seed, index)")
    args = parser.parse_args(argv)
    side = gravel_texture().shape[0]
    if not 1 <= args.size <= side:
        raise ValueError(f"--size must be from 1 to {side} (the texture the pairs are cut from), got {args.size}")
    try:
        truth = make_truth(args.flavour, (args.size, args.size), args.noise_std)
        pairs = SyntheticPairs(truth, args.pairs, seed=args.seed, gain_std=args.gain_std, offset_std=args.offset_std)
        start = time.perf_counter()
        source = f"enmi-make-pairs {args.flavour} noise_std={args.noise_std} seed={args.seed}"
        count = write_pairs(args.out, pairs, image_format=args.format, truth=truth, source=source)
    except (ValueError, TypeError) as error:  # the library names its parameters: name the flags instead
        message = with_flag_names(str(error), FLAGS)
        if message == str(error):
            raise
        raise type(error)(message) from None
    seconds = time.perf_counter() - start
    megabytes = sum(path.stat().st_size for path in Path(args.out).rglob("*") if path.is_file()) / 2**20
    print(
        f"wrote {count} {args.flavour}-like pairs of {args.size}x{args.size} to {args.out} ({megabytes:.1f} MB) "
        f"in {seconds:.1f} s; fit a mask to them with enmi-fit-mask --data.root {args.out}"
    )


if __name__ == "__main__":
    main()
