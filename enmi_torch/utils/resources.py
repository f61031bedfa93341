"""The default config files (``configs/`` of a clone, the package data ``enmi_torch.configs`` of an install).

pyproject.toml maps the package ``enmi_torch.configs`` to the top-level ``configs/`` folder: one copy, read in place
from a clone (editable install or ``PYTHONPATH``) and shipped inside the wheel.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

# The folder above the package: a clone's root when ``enmi_torch`` is imported from a source tree.
_SOURCE_ROOT = Path(__file__).resolve().parents[2]


def config_dir() -> Path:
    """The default configs' folder: the clone's ``configs/`` from a source tree, else the installed package data."""
    if (_SOURCE_ROOT / "pyproject.toml").is_file() and (_SOURCE_ROOT / "configs" / "__init__.py").is_file():
        return _SOURCE_ROOT / "configs"  # the clone's own files, never those of another install on the path
    try:
        return Path(str(resources.files("enmi_torch.configs")))
    except ModuleNotFoundError:
        raise FileNotFoundError(
            "the default configs (package enmi_torch.configs) are not installed: reinstall enmi_torch"
        ) from None


def config_file(name: str) -> Path:
    """The default config file ``name`` (``"fit_mask.yaml"``, ``"camera/paper.yaml"``), checked to exist."""
    path = config_dir() / name
    if not path.is_file():
        raise FileNotFoundError(f"the default config {name!r} is missing from {config_dir()}: reinstall enmi_torch")
    return path
