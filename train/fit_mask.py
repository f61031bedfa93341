"""``python train/fit_mask.py`` runs ``enmi-fit-mask``: learn a per-pixel noise-variance mask (``--help``)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the clone's enmi_torch, installed or not

from enmi_torch.cli.fit_mask import main

if __name__ == "__main__":
    main()
