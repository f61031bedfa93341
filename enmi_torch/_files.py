"""Reading ``.npy`` files from users: no pickles, and a message that says what is wrong with the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

NPY_MAGIC = b"\x93NUMPY"


def load_npy(path: str | Path) -> np.ndarray:
    """``np.load(path, allow_pickle=False)``, refusing first a file that is not in NumPy's ``.npy`` format.

    NumPy reads a file without the ``.npy`` header (a text file named ``.npy``, say) as a pickle and then reports
    "pickled data"; this says instead that the file is not a ``.npy`` file.

    Raises:
        ValueError: the file is not a ``.npy`` file, or holds pickled objects.
        OSError: the file cannot be opened.
    """
    with Path(path).open("rb") as handle:
        magic = handle.read(len(NPY_MAGIC))
    if magic != NPY_MAGIC:
        raise ValueError("not a .npy file: it lacks the NumPy header (write it with numpy.save, not as text)")
    return np.load(path, allow_pickle=False)
