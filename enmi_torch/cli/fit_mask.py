"""``enmi-fit-mask`` (also ``python train/fit_mask.py``): learn a per-pixel noise-variance mask from image pairs.

The command itself is :func:`enmi_torch.training.fit_mask.fit_mask`; it needs Lightning, imported only when the
command runs.
"""

from __future__ import annotations

from collections.abc import Sequence

from enmi_torch.cli._command import fail, run_command

PROG = "enmi-fit-mask"


def main(argv: Sequence[str] | None = None) -> None:
    """Console entry point: ``enmi-fit-mask --help``."""
    try:
        from enmi_torch.training.fit_mask import fit_mask
    except ImportError as error:
        fail(PROG, f"{error}: training needs the train extra, pip install -e '.[train]'")
    run_command(PROG, fit_mask, argv)
