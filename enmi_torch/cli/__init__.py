"""The command-line tools, installed as console scripts by ``pip install -e .`` (see pyproject.toml).

====================  =============================================  ==============================================
console script        entry point                                    also runs as
====================  =============================================  ==============================================
enmi-fit-mask         ``enmi_torch.cli.fit_mask:main``               ``python -m enmi_torch.cli.fit_mask``
enmi-localize         ``enmi_torch.cli.localize:main``               ``python -m enmi_torch.cli.localize``
enmi-reproduce-paper  ``enmi_torch.cli.reproduce_paper:main``        ``python -m enmi_torch.cli.reproduce_paper``
enmi-make-pairs       ``enmi_torch.cli.make_pairs:main``             ``python -m enmi_torch.cli.make_pairs``
enmi-example          ``enmi_torch.cli.example:main``                ``python -m enmi_torch.cli.example``
====================  =============================================  ==============================================

Every command explains itself with ``--help`` (what it does, an example, the defaults), writes under ``runs/`` of
the current folder unless told otherwise, and reports a user mistake in one line with exit code 2 (``--debug``
shows the traceback). The parsing, help and one-line errors they share are in :mod:`enmi_torch.utils.command`.
"""
