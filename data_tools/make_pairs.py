"""Write synthetic local/prior pairs to a folder in the enmi_torch.data.pairs format.

    python data_tools/make_pairs.py OUT_FOLDER --pairs 2000 --flavour lidar --size 128 --noise-std 12
    python train/fit_mask.py --data.root OUT_FOLDER

The folder gets local/, prior/, valid/ (one file per pair, .npy or 8-bit .png), meta.json and the true variance
map truth_variance.npy (NaN where invalid), so that the training dashboards can compare the learned mask with it.
"""

from __future__ import annotations

import argparse
import time

from enmi_torch.data import SyntheticPairs, make_truth, write_pairs


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", help="new (or empty) folder to write")
    parser.add_argument("--pairs", type=int, default=2000, help="number of pairs (default 2000)")
    parser.add_argument("--flavour", choices=("lidar", "camera"), default="lidar", help="noise field (default lidar)")
    parser.add_argument("--size", type=int, default=128, help="image side in pixels (default 128, at most 512)")
    parser.add_argument("--noise-std", type=float, default=12.0, help="RMS noise std over valid pixels (default 12)")
    parser.add_argument("--gain-std", type=float, default=0.0, help="std of a per-pair intensity gain (default 0)")
    parser.add_argument("--offset-std", type=float, default=0.0, help="std of a per-pair intensity offset (default 0)")
    parser.add_argument("--format", choices=("npy", "png"), default="npy", help="image files (default npy)")
    parser.add_argument("--seed", type=int, default=0, help="pairs are a function of (seed, index) (default 0)")
    args = parser.parse_args(argv)
    truth = make_truth(args.flavour, (args.size, args.size), args.noise_std)
    pairs = SyntheticPairs(truth, args.pairs, seed=args.seed, gain_std=args.gain_std, offset_std=args.offset_std)
    start = time.perf_counter()
    source = f"data_tools/make_pairs.py {args.flavour} noise_std={args.noise_std} seed={args.seed}"
    count = write_pairs(args.out, pairs, image_format=args.format, truth=truth, source=source)
    seconds = time.perf_counter() - start
    print(f"wrote {count} {args.flavour}-like pairs of {args.size}x{args.size} to {args.out} in {seconds:.1f} s")


if __name__ == "__main__":
    main()
