"""The commands' default configs and the paper's plotted points, installed as the package data ``enmi_torch.configs``.

One copy: pyproject.toml maps the package ``enmi_torch.configs`` to this folder, so a wheel ships these files;
``enmi_torch.utils.resources.config_file`` finds them in a clone and in an install alike.
"""
