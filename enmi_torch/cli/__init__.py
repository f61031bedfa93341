"""The command-line tools, installed as console scripts by ``pip install -e .`` (see pyproject.toml).

====================  =============================================  ===========================================
console script        entry point                                    also runs as (from the repository root)
====================  =============================================  ===========================================
enmi-fit-mask         ``enmi_torch.cli.fit_mask:main``               ``python train/fit_mask.py``
enmi-localize         ``enmi_torch.localization.cli:main``           ``python -m enmi_torch.localization``
enmi-reproduce-paper  ``enmi_torch.cli.reproduce_paper:main``        ``python data_tools/reproduce_paper.py``
enmi-make-pairs       ``enmi_torch.cli.make_pairs:main``             ``python data_tools/make_pairs.py``
====================  =============================================  ===========================================

Every command explains itself with ``--help`` (what it does, an example, the defaults), writes under ``runs/`` of
the current folder unless told otherwise, and reports a user mistake in one line with exit code 2 (``--debug``
shows the traceback).
"""
