"""README figure: the masks learned by ``python train/fit_mask.py`` from lidar-like and camera-like pairs.

    python data_tools/figure_fit_mask.py

Runs the default configuration (configs/fit_mask.yaml) twice, once per synthetic flavour, and stacks the two mask
figures the command writes (learned, empirical and true variance on one colour scale, and one held-out residual)
into data_tools/figures/fit_mask.png.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from train.fit_mask import main as fit_mask  # noqa: E402

OUTPUT = ROOT / "data_tools" / "figures" / "fit_mask.png"


def main() -> None:
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
    OUTPUT.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(padded)).quantize(colors=256).save(OUTPUT, optimize=True)
    print(f"wrote {OUTPUT} ({OUTPUT.stat().st_size / 1024:.0f} KB)")


if __name__ == "__main__":
    main()
