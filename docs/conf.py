"""Sphinx configuration of the API reference: ``sphinx-build -W --keep-going -b html docs runs/docs``.

The API pages are written at build time from ``__all__``: ``enmi_torch`` (grouped by topic) and, for each public
subpackage, the names it adds; so the site shows the public names only and never drifts from the code.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the clone's enmi_torch, installed or not

import enmi_torch  # noqa: E402

project = "enmi_torch"
author = "enmi_torch contributors"
copyright = f"2026, {author}"  # the footer; Sphinx reads this name
release = version = enmi_torch.__version__
extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon", "myst_parser"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build"]
html_theme = "furo"
html_title = f"enmi_torch {release}"
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_description_target = "documented"  # types beside the documented arguments, no second list
autodoc_default_options = {"show-inheritance": False}
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_use_ivar = True  # "Attributes:" as fields: autodoc documents the attributes themselves once
myst_heading_anchors = 3
# The model page's equations: $...$ and labelled $$...$$ blocks (dollarmath), LaTeX environments such as aligned
# (amsmath); MathJax renders them.
myst_enable_extensions = ["dollarmath", "amsmath"]
# Docstrings name the role of an argument in double backquotes; a bare `x` is code, not a cross-reference.
default_role = "code"
# Type hints name classes of torch, kornia and Lightning that this site does not document.
nitpicky = False

# Top-level names grouped by the module that defines them: (title, module prefixes).
TOPICS = [
    ("Scores", ("enmi_torch.scores",)),
    ("Losses", ("enmi_torch.losses",)),
    ("Variance maps", ("enmi_torch.variance",)),
    ("Localization", ("enmi_torch.localization", "enmi_torch.placement")),
    ("Registration", ("enmi_torch.registration",)),
    ("Tracking", ("enmi_torch.tracking",)),
    ("Road camera and rectification", ("enmi_torch.geometry",)),
]
# Public subpackages and modules: the names each adds to the top level's.
SUBPACKAGES = {
    "enmi_torch.functional": "The functions behind the scores and losses: values, surfaces, histograms, bin weights.",
    "enmi_torch.scores": "Score families beyond the top level.",
    "enmi_torch.losses": "Loss modules beyond the top level.",
    "enmi_torch.localization": "The search beyond the top level.",
    "enmi_torch.registration": "Registration beyond the top level.",
    "enmi_torch.variance": "Variance bases and the perspective variance.",
    "enmi_torch.tracking": "The filter's steps: belief, health, calibration.",
    "enmi_torch.placement": "The FFT machinery the score surfaces share.",
    "enmi_torch.maps": "Real maps: windows of GeoTIFF/COG, .npy and PNG maps, and world coordinates (the geo extra).",
    "enmi_torch.data": "Pairs for fitting a variance mask: folders, synthetic data, the Lightning data module; the "
    "example pair bundled with the library (Landsat 5 over Nanjing, 2000 and 2002).",
    "enmi_torch.simulation": "The paper's simulation (Fig. simPerformance).",
}
# Modules whose docstrings a subpackage's page shows (each opens with its model and links to docs/model.md).
MODULE_DOCSTRINGS = {
    "enmi_torch.scores": [
        f"enmi_torch.scores.{name}"
        for name in "ecr shrunk_response ecr_model_variance ecr_regional_misfit censoring ecr_censored".split()
        + "enmi nmi ncc mixture".split()
    ],
}
TRAINING = {
    "enmi_torch.training.mask_module": ["MaskFitModule"],
    "enmi_torch.training.held_out": ["localization_trials", "calibrate_levels", "LevelCalibration"],
    "enmi_torch.training.logger": ["MaskLogger"],
    "enmi_torch.training.fit_mask": ["fit_mask"],
}


def _entry(module: str, name: str) -> str:
    target = getattr(importlib.import_module(module), name)
    kind = "autoclass" if isinstance(target, type) else "autofunction" if callable(target) else "autodata"
    options = "\n   :members:\n" if kind == "autoclass" else ""
    return f".. {kind}:: {module}.{name}{options}\n"


def _top_level() -> str:
    lines = ["enmi_torch", "==========", "", ".. module:: enmi_torch", "", enmi_torch.__doc__.strip(), ""]
    grouped = {title: [] for title, _ in TOPICS}
    for name in enmi_torch.__all__:
        module = getattr(getattr(enmi_torch, name), "__module__", "") or ""
        title = next((title for title, prefixes in TOPICS if module.startswith(prefixes)), None)
        if title is None:
            raise ValueError(f"enmi_torch.{name} (from {module!r}) belongs to no topic of docs/conf.py's TOPICS")
        grouped[title].append(name)
    for title, names in grouped.items():
        lines += [title, "-" * len(title), ""]
        lines += [_entry("enmi_torch", name) for name in sorted(names, key=str.lower)]
    return "\n".join(lines)


def _subpackage(module_name: str, summary: str) -> str:
    module = importlib.import_module(module_name)
    names = getattr(module, "__all__", None)
    if names is None:
        raise ValueError(f"{module_name} has no __all__: the docs list public names only")
    added = [name for name in names if name not in enmi_torch.__all__]
    shared = [name for name in names if name in enmi_torch.__all__]
    lines = [module_name, "=" * len(module_name), "", f".. module:: {module_name}", "", summary, ""]
    if shared:
        lines += ["Also here, documented at the top level: " + ", ".join(f":obj:`enmi_torch.{n}`" for n in shared), ""]
    lines += [_entry(module_name, name) for name in added]
    if module_name in MODULE_DOCSTRINGS:  # last: an automodule sets the current module for what follows
        lines += ["The modules and their models", "-" * 28, ""]
        lines += [f".. automodule:: {name}\n" for name in MODULE_DOCSTRINGS[module_name]]
    return "\n".join(lines)


def _training() -> str:
    title = "enmi_torch.training"
    summary = "The variance-mask fit behind ``enmi-fit-mask`` (needs the ``train`` extra)."
    lines = [title, "=" * len(title), "", summary, ""]
    for module, names in TRAINING.items():
        lines += [_entry(module, name) for name in names]
    return "\n".join(lines)


def _write_api_pages(app) -> None:
    folder = Path(app.srcdir) / "api"
    folder.mkdir(exist_ok=True)
    pages = {"enmi_torch": _top_level(), "enmi_torch.training": _training()}
    pages.update({name: _subpackage(name, summary) for name, summary in SUBPACKAGES.items()})
    for name, text in pages.items():
        path = folder / f"{name}.rst"
        if not path.is_file() or path.read_text() != text:  # unchanged pages keep their time: no needless rebuild
            path.write_text(text)


def _skip_member(app, what, name, obj, skip, options):
    """Leave out what tells a reader nothing: NamedTuple field aliases (the class lists its fields), ``extra_repr``."""
    if name == "extra_repr" or (getattr(obj, "__doc__", None) or "").startswith("Alias for field number"):
        return True
    return None


def _no_type_docstring(app, what, name, obj, options, lines):
    """A constant without its own docstring shows none, not its type's (``float``: "Convert a string or number ...")."""
    if what in ("data", "attribute") and lines and type(obj).__doc__ and "\n".join(lines).strip() in type(obj).__doc__:
        lines[:] = []


def setup(app) -> None:
    """Write the API pages before the build; trim autodoc's noise."""
    app.connect("builder-inited", _write_api_pages)
    app.connect("autodoc-skip-member", _skip_member)
    app.connect("autodoc-process-docstring", _no_type_docstring)
