"""``python data_tools/make_pairs.py`` runs ``enmi-make-pairs``: write synthetic local/prior pairs (``--help``)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the clone's enmi_torch, installed or not

from enmi_torch.cli.make_pairs import main

if __name__ == "__main__":
    main()
