"""Reading files that users name: ``.npy`` arrays (header checked first), images, and plain torch files (no pickle).

``numpy.load`` allocates the array its header states before reading the data, so a 4 KiB file whose header states
``(100000, 100000)`` float64 asks for 74.5 GiB. :func:`read_npy` reads the header alone first and refuses a file that
holds fewer bytes than it states, an array over the memory budget, pickles and arrays of Python objects; every
message names the file and where its path came from (a command-line flag or an argument).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from enmi_torch.utils.budget import budget_error, format_bytes, within_budget

_MAGIC = np.lib.format.MAGIC_PREFIX
_HEADER_READERS = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}


def read_npy(path: str | Path, source: str) -> np.ndarray:
    """The array of the ``.npy`` file at ``path``, read without pickles once its header is found consistent.

    Args:
        path: the file.
        source: where the path came from, named in messages: a flag (``"--map"``) or an argument (``"path"``).

    Raises:
        ValueError: naming ``source`` and the file, when it cannot be opened, is not a ``.npy`` file (a pickle, say),
            has a damaged header, holds Python objects, or holds fewer bytes than its header states.
        MemoryBudgetError: when the array is larger than the memory budget
            (:func:`~enmi_torch.utils.budget.set_memory_budget`).

    Example:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "map.npy"
        >>> np.save(path, np.eye(2))
        >>> read_npy(path, "--map")
        array([[1., 0.],
               [0., 1.]])
    """
    path = Path(path)
    named = f"{source} {str(path)!r}"
    try:
        stream = path.open("rb")
    except OSError as error:
        raise ValueError(f"{named} cannot be read: {error.strerror or error}") from None
    with stream:
        start = stream.read(len(_MAGIC))
        if start != _MAGIC:
            raise ValueError(f"{named} is not a .npy file: {_describe(start)}")
        stream.seek(0)
        try:
            version = np.lib.format.read_magic(stream)
            if version not in _HEADER_READERS:
                raise ValueError(f"format version {version[0]}.{version[1]} is not read here (1.0 and 2.0 are)")
            shape, _, dtype = _HEADER_READERS[version](stream)
            if any(size < 0 for size in shape):
                raise ValueError(f"negative size in shape {shape}")
        except Exception as error:  # numpy parses the header text with ast and tokenize, which raise their own kinds
            raise ValueError(f"{named} has a damaged .npy header: {error}") from None
        if dtype.hasobject:
            raise ValueError(f"{named} is refused: it holds Python objects (dtype {dtype}), which load only as pickles")
        stated = math.prod(shape) * dtype.itemsize
        held = os.fstat(stream.fileno()).st_size - stream.tell()
        if held < stated:
            raise ValueError(
                f"{named} is truncated or its header is wrong: the header states a {shape} {dtype} array of "
                f"{format_bytes(stated)}, the file holds {format_bytes(held)} of data"
            )
        if not within_budget(stated):
            raise budget_error(stated, named, f"its {shape} {dtype} array", "crop or downsample the array")
        stream.seek(0)
        return np.lib.format.read_array(stream, allow_pickle=False)


def _describe(start: bytes) -> str:
    """What a file that does not start with NumPy's header seems to be, from its first bytes."""
    if not start:
        return "it is empty"
    if start[:1] == b"\x80":
        return "it is a Python pickle, which is never loaded"
    if start[:2] == b"PK":
        return "it is a zip archive (an .npz or a torch file?)"
    if start[:4] == b"\x89PNG":
        return "it is a PNG image; give it the .png suffix"
    return f"it starts with {start!r}, not with NumPy's header {_MAGIC!r}"


def read_image(path: str | Path, source: str) -> np.ndarray:
    """A single-channel ``(H, W)`` image from a ``.npy`` file (:func:`read_npy`) or a grey PNG (8 or 16 bits kept).

    The one image reader of the library's commands and pair folders.

    Raises:
        ValueError: naming ``source`` and the file, when it cannot be read, has another suffix, is a colour PNG or
            does not hold one ``(H, W)`` channel.
    """
    path = Path(path)
    named = f"{source} {str(path)!r}"
    suffix = path.suffix.lower()
    if suffix == ".npy":
        image = read_npy(path, source)
    elif suffix == ".png":
        try:
            from PIL import Image

            with Image.open(path) as opened:
                if opened.mode not in ("L", "I;16", "I;16B", "I", "1"):
                    raise ValueError(f"expected a single-channel (grey) PNG, got mode {opened.mode}")
                image = np.array(opened)  # a writable copy: torch.as_tensor warns on a read-only array
        except ImportError as error:
            raise ValueError(f"{named}: reading PNG needs Pillow (pip install -e '.[train]')") from error
        except Exception as error:  # every decoder failure becomes one message naming the file
            raise ValueError(f"{named} is not a readable image: {error}") from None
    else:
        raise ValueError(f"{named} must be a .npy or .png file")
    if np.iscomplexobj(image):
        raise ValueError(f"{named} must hold real values, got complex dtype {image.dtype}")
    if image.ndim == 3 and image.shape[0] == 1:
        image = image[0]
    if image.ndim != 2:
        raise ValueError(f"{named} must hold a single-channel (H, W) image, got shape {image.shape}")
    return image


def check_file_to_write(path: str | Path, source: str) -> Path:
    """``path`` as a :class:`~pathlib.Path` if a file can be written there; else a ``ValueError`` naming ``source``.

    Refused: an existing folder at ``path``, a file where one of its folders should be, a folder that cannot be
    written. ``source`` is how the caller's user named the path (an argument, a command-line flag).

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     check_file_to_write(folder, "path")
        Traceback (most recent call last):
        ...
        ValueError: path must name a file to write, got the existing folder '...'
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{source} must name a file to write, got the existing folder {str(path)!r}")
    existing = next(parent for parent in path.absolute().parents if parent.exists())
    if not existing.is_dir():
        raise ValueError(f"{source} {str(path)!r} cannot be written: {str(existing)!r} on its path is a file")
    if not os.access(existing, os.W_OK):
        raise ValueError(f"{source} {str(path)!r} cannot be written: {str(existing)!r} is read-only")
    return path


def check_folder_to_write(path: str | Path, source: str) -> Path:
    """``path`` as a :class:`~pathlib.Path` if it is or can become a folder to write in; else a ``ValueError``.

    Refused: a file at ``path`` or on its way (``a/b`` where ``a`` is a file), a folder that cannot be written. The
    message names ``source``, how the caller's user named the path (an argument, a command-line flag).

    Example:
        >>> import tempfile
        >>> with tempfile.NamedTemporaryFile() as file:
        ...     check_folder_to_write(file.name, "--output_dir")
        Traceback (most recent call last):
        ...
        ValueError: --output_dir must be a folder, got '...', which is a file
    """
    path = Path(path)
    existing = next(folder for folder in (path, *path.absolute().parents) if folder.exists())
    if not existing.is_dir():
        which = "which is" if existing == path else f"but {str(existing)!r} on its path is"
        raise ValueError(f"{source} must be a folder, got {str(path)!r}, {which} a file")
    if not os.access(existing, os.W_OK):
        raise ValueError(f"{source} {str(path)!r} cannot be written: {str(existing)!r} is read-only")
    return path


def load_plain_torch(path: str | Path, what: str) -> object:
    """``torch.load(path, weights_only=True)`` on the CPU: tensors and primitives only, never a pickled object.

    Anything else (a pickle of arbitrary objects, a damaged or foreign file) raises ``ValueError`` naming the file and
    ``what`` it should have been (``"a plain checkpoint"``).
    """
    import torch

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except MemoryError:
        raise
    except Exception as error:  # the weights-only unpickler raises anything (IndexError, KeyError) on a foreign file
        detail = str(error) if isinstance(error, (RuntimeError, OSError, ValueError)) else repr(error)
        raise ValueError(f"{path} is refused: it is not {what} that loads with weights_only=True ({detail})") from None


def read_json(path: str | Path, source: str) -> object:
    """The JSON value of the text file at ``path``; every failure is one ``ValueError`` naming ``source`` and the file.

    Refused: a file that cannot be opened, is not UTF-8 text (a binary file), is not JSON, or nests deeper than
    Python's parser can follow (``RecursionError``). ``NaN`` and ``Infinity`` are read as Python's ``json`` reads them
    (floats): checking the values (finite numbers, an object, its keys) is the caller's, which can name the key.
    """
    import json

    named = f"{source} {str(path)!r}"
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as error:
        raise ValueError(f"{named} cannot be read: {error.strerror or error}") from None
    except UnicodeDecodeError:
        raise ValueError(f"{named} is not readable JSON: it is not UTF-8 text (a binary file?)") from None
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError(f"{named} is not readable JSON: it nests too deeply") from None
    except ValueError as error:  # json.JSONDecodeError
        raise ValueError(f"{named} is not readable JSON: {error}") from None


def describe_json(value: object) -> str:
    """A JSON value's kind and a short excerpt, for messages: ``a list [1, 2]``, ``null``, ``a string 'x'``."""
    kinds = {dict: "an object", list: "a list", str: "a string", bool: "a boolean", int: "a number", float: "a number"}
    if value is None:
        return "null"
    text = repr(value)
    return f"{kinds.get(type(value), type(value).__name__)} {text if len(text) <= 60 else text[:57] + '...'}"


def yaml_error_message(path: str | Path, source: str, error: BaseException) -> str:
    """One line for a YAML file that did not parse: ``source``, the file, what went wrong and where.

    ``error`` is what ``yaml.safe_load`` raised: a ``yaml.YAMLError`` (a syntax error, or a tag such as
    ``!!python/object`` that the safe loader refuses without running anything), ``UnicodeDecodeError`` (a binary
    file) or ``RecursionError`` (nesting deeper than the parser follows).
    """
    named = f"{source} {str(path)!r}"
    if isinstance(error, UnicodeDecodeError):
        return f"{named} is not readable YAML: it is not UTF-8 text (a binary file?)"
    if isinstance(error, RecursionError):
        return f"{named} is not readable YAML: it nests too deeply"
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    mark = getattr(error, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    if "constructor for the tag" in problem:
        problem += " (only plain YAML is read: tags such as !!python/... are refused and nothing is run)"
    return f"{named} is not readable YAML: {problem}{where}"
