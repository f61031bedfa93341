"""README figure: the masks learned by ``enmi-fit-mask`` from lidar-like and camera-like pairs.

    python -m data_tools.experiments.mask.figure_fit_mask  # writes runs/fit_mask.png
    # regenerates the README figure
    python -m data_tools.experiments.mask.figure_fit_mask --figure docs/images/fit_mask.png

Runs the default configuration (configs/fit_mask.yaml) twice, once per synthetic flavour, and stacks the two mask
figures the command writes (learned, empirical and true variance on one colour scale, and one held-out residual).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from enmi_torch.training.fit_mask import fit_mask


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--figure", type=Path, default=Path("runs/fit_mask.png"), help="PNG to write")
    output = parser.parse_args().figure
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for flavour in ("lidar", "camera"):
            summary = fit_mask(
                [
                    *("--trainer.logger.init_args.save_dir", folder, "--trainer.enable_progress_bar", "false"),
                    *("--data.flavour", flavour),
                ]
            )
            with Image.open(summary["files"]["png"]) as image:
                rows.append(np.asarray(image.convert("RGB")))
    width = max(row.shape[1] for row in rows)
    padded = [np.pad(row, ((0, 0), (0, width - row.shape[1]), (0, 0)), constant_values=255) for row in rows]
    output.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(padded)).quantize(colors=256).save(output, optimize=True)
    print(f"wrote {output} ({output.stat().st_size / 1024:.0f} KB)")


if __name__ == "__main__":
    main()
