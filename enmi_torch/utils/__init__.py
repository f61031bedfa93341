"""Utilities the package shares: input checks, the memory budget, image layouts, files, configs, resources, commands.

Importable by users (``from enmi_torch.utils.budget import memory_budget``), not re-exported at the top level.
"""
