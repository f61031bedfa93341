import numpy as np
import pytest

from enmi_torch._files import load_npy


def test_load_npy_reads_arrays_and_names_what_is_wrong_with_other_files(tmp_path):
    np.save(tmp_path / "map.npy", np.arange(6.0).reshape(2, 3))
    np.testing.assert_array_equal(load_npy(tmp_path / "map.npy"), np.arange(6.0).reshape(2, 3))
    np.savetxt(tmp_path / "text.npy", np.ones((2, 2)))
    with pytest.raises(ValueError, match=r"not a \.npy file: it lacks the NumPy header"):
        load_npy(tmp_path / "text.npy")
    np.save(tmp_path / "objects.npy", np.array([{}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match="allow_pickle=False"):
        load_npy(tmp_path / "objects.npy")
    with pytest.raises(FileNotFoundError):
        load_npy(tmp_path / "missing.npy")
