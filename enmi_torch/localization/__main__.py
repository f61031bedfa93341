"""``python -m enmi_torch.localization``: the ``enmi-localize`` command."""

from enmi_torch.localization.cli import main

main()
