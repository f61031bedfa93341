"""Load a script of ``data_tools/`` (not a package) as a module, for the tests of its functions."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

DATA_TOOLS = Path(__file__).resolve().parents[1] / "data_tools"


def load_data_tool(relative: str, name: str) -> ModuleType:
    """``data_tools/<relative>`` run as module ``name`` (registered in ``sys.modules``: dataclasses look it up)."""
    spec = importlib.util.spec_from_file_location(name, DATA_TOOLS / relative)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
