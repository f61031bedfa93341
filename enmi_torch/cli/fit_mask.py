"""``enmi-fit-mask`` (also ``python -m enmi_torch.cli.fit_mask``): learn a per-pixel noise-variance mask from pairs.

The command itself is :func:`enmi_torch.training.fit_mask.fit_mask`; it needs Lightning, imported only when the
command runs. ``--help`` and the mistakes that the option list alone shows (a misspelt option, a word where a number
goes) are answered without it (:mod:`enmi_torch.cli.fit_mask_quick`).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from enmi_torch.cli.fit_mask_quick import PROG, quick_answer
from enmi_torch.utils.command import fail, run_command


def main(argv: Sequence[str] | None = None) -> None:
    """Console entry point: ``enmi-fit-mask --help``."""
    arguments = list(sys.argv[1:] if argv is None else argv)
    quick_answer(arguments)
    try:
        from enmi_torch.training.fit_mask import fit_mask
    except ImportError as error:
        fail(
            PROG,
            f"{error}: training needs the train extra: pip install 'enmi_torch[train]' "
            "(in a clone: pip install -e '.[train]')",
        )
    run_command(PROG, fit_mask, arguments)


if __name__ == "__main__":
    main()
