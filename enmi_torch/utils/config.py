"""Reading the sections of a YAML configuration (``configs/``) with errors that name the file, section and key."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any


def load_yaml_section(path: str | Path, key: str, source: str = "config file") -> Mapping[str, Any]:
    """The mapping under top-level ``key`` of the YAML file at ``path``.

    A file that is not plain YAML (a syntax error, a ``!!python`` tag, binary, too deeply nested) raises one
    ``ValueError`` naming ``source`` and the file (:func:`~enmi_torch.utils.files.yaml_error_message`); nothing in
    it runs.
    """
    import yaml

    from enmi_torch.utils.files import yaml_error_message

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{source} {str(path)!r} does not exist")
    try:
        with path.open() as stream:
            document = yaml.safe_load(stream)
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as error:
        raise ValueError(yaml_error_message(path, source, error)) from None
    if not isinstance(document, Mapping):
        raise ValueError(f"config file {str(path)!r} must hold a mapping at top level, got {type(document).__name__}")
    if key not in document:
        raise ValueError(f"config file {str(path)!r} has no section {key!r}; it has {sorted(document)}")
    section = document[key]
    if not isinstance(section, Mapping):
        raise ValueError(f"section {key!r} of {str(path)!r} must be a mapping, got {type(section).__name__}")
    return section


def check_config_keys(name: str, config: Any, required: Sequence[str], optional: Sequence[str] = ()) -> None:
    """Raise unless ``config`` is a mapping with every ``required`` key and no key outside ``required + optional``."""
    if not isinstance(config, Mapping):
        raise TypeError(f"{name} config must be a mapping, got {type(config).__name__}")
    missing = [key for key in required if key not in config]
    unknown = sorted(str(key) for key in config if key not in (*required, *optional))
    if missing or unknown:
        raise ValueError(
            f"{name} config must have keys {list(required)} (optional: {list(optional)}), "
            f"got missing {missing} and unknown {unknown}"
        )
