"""``python data_tools/reproduce_paper.py`` runs ``enmi-reproduce-paper``: the paper's Fig. simPerformance."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the clone's enmi_torch, installed or not

from enmi_torch.cli.reproduce_paper import main

if __name__ == "__main__":
    main()
