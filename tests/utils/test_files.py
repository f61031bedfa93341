"""``.npy`` files named by users: headers checked before reading, messages naming the file and where it came from."""

import json
import os
import pickle
import re

import numpy as np
import pytest

from enmi_torch import LearnedVariance
from enmi_torch.cli.localize import main
from enmi_torch.data import PairDataset, SyntheticPairs, lidar_truth, write_pairs
from enmi_torch.utils.budget import MemoryBudgetError, memory_budget
from enmi_torch.utils.files import check_file_to_write, check_folder_to_write, read_image, read_npy

TRUNCATED = (
    r"is truncated or its header is wrong: the header states a \(100000, 100000\) float64 array of 74\.5 GiB, "
    r"the file holds 4\.0 KiB of data"
)


def _giant_header(path):
    """A 4 KiB ``.npy`` whose header states a (100000, 100000) float64 array (74.5 GiB)."""
    with path.open("wb") as stream:
        np.lib.format.write_array_header_1_0(
            stream, {"descr": "<f8", "fortran_order": False, "shape": (100000, 100000)}
        )
        stream.write(bytes(4096))
    return path


@pytest.fixture
def local_file(tmp_path):
    path = tmp_path / "local.npy"
    np.save(path, np.random.default_rng(0).uniform(0, 255, (16, 16)).astype(np.float32))
    return str(path)


def test_a_giant_header_is_refused_by_the_mask_loader(tmp_path):
    with pytest.raises(ValueError, match=rf"^path '.*big\.npy' {TRUNCATED}"):
        LearnedVariance.load(_giant_header(tmp_path / "big.npy"))


def _fails_with(capsys, arguments, pattern):
    """The localize command exits with code 2 and one ``enmi-localize: error: ...`` line matching ``pattern``."""
    with pytest.raises(SystemExit) as exited:
        main(arguments)
    assert exited.value.code == 2
    message = capsys.readouterr().err
    assert message.count("\n") == 1 and re.match(rf"enmi-localize: error: {pattern}", message), message


def test_a_giant_header_is_refused_by_the_command_line(tmp_path, local_file, capsys):
    big = str(_giant_header(tmp_path / "big.npy"))
    _fails_with(capsys, ["--map", big, "--local", local_file, "--variance", "4"], rf"--map '.*big\.npy' {TRUNCATED}")
    _fails_with(
        capsys, ["--map", local_file, "--local", local_file, "--variance", big], rf"--variance '.*big\.npy' {TRUNCATED}"
    )


def test_a_giant_header_is_refused_by_the_pair_reader(tmp_path):
    truth = lidar_truth((12, 10))
    root = tmp_path / "pairs"
    write_pairs(root, SyntheticPairs(truth, 2, seed=1))
    _giant_header(root / "prior" / "000001.npy")
    dataset = PairDataset(root)
    dataset[0]
    with pytest.raises(ValueError, match=rf"^pair image '.*prior/000001\.npy' {TRUNCATED}"):
        dataset[1]


def test_the_command_line_names_the_flag_of_a_pickle_or_a_random_file(tmp_path, local_file, capsys):
    pickled = tmp_path / "pickled.npy"
    pickled.write_bytes(pickle.dumps({"a": 1}))
    noise = tmp_path / "noise.npy"
    noise.write_bytes(np.random.default_rng(1).integers(0, 256, 300, dtype=np.uint8).tobytes())
    arguments = ["--local", local_file, "--variance", "4"]
    _fails_with(
        capsys,
        ["--map", str(pickled), *arguments],
        r"--map '.*pickled\.npy' is not a \.npy file: it is a Python pickle",
    )
    _fails_with(
        capsys,
        ["--map", local_file, *arguments, "--local-mask", str(noise)],
        r"--local-mask '.*noise\.npy' is not a \.npy file: it starts with b'",
    )
    _fails_with(
        capsys,
        ["--map", local_file, "--local", str(tmp_path / "missing.png"), "--variance", "4"],
        r"--local: no such file '.*missing\.png'",
    )


def test_an_array_over_the_budget_is_refused_before_reading(tmp_path, local_file, capsys):
    path = tmp_path / "map.npy"
    np.save(path, np.zeros((64, 64)))
    with memory_budget(10_000):
        with pytest.raises(MemoryBudgetError, match=r"^--map '.*map\.npy' needs about 32\.0 KiB for its \(64, 64\)"):
            read_npy(path, "--map")
        _fails_with(
            capsys,
            ["--map", str(path), "--local", local_file, "--variance", "4"],
            r"--map '.*map\.npy' needs about 32\.0 KiB .* budget of 9\.8 KiB",
        )
    assert read_npy(path, "--map").shape == (64, 64)


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"", "is not a .npy file: it is empty"),
        (b"PK\x03\x04rest", r"is not a \.npy file: it is a zip archive"),
        (b"\x89PNG\r\n\x1a\n", r"is not a \.npy file: it is a PNG image"),
        (b"\x93NUMPY\x01\x00\x10\x00{'descr': '<f8',", r"has a damaged \.npy header"),
        (b"\x93NUMPY\x07\x00", r"has a damaged \.npy header"),
    ],
)
def test_damaged_files_are_named(tmp_path, content, match):
    path = tmp_path / "bad.npy"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=rf"^path '.*bad\.npy' {match}"):
        read_npy(path, "path")


def test_object_arrays_and_missing_files_are_refused(tmp_path):
    path = tmp_path / "objects.npy"
    np.save(path, np.array([{}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=r"objects\.npy' is refused: it holds Python objects \(dtype object\)"):
        read_npy(path, "--map")
    with pytest.raises(ValueError, match=r"^--map '.*missing\.npy' cannot be read: No such file"):
        read_npy(tmp_path / "missing.npy", "--map")


def test_plain_arrays_round_trip(tmp_path):
    array = np.arange(12, dtype=np.int16).reshape(3, 4)
    np.save(tmp_path / "plain.npy", array)
    np.save(tmp_path / "fortran.npy", np.asfortranarray(array.astype(np.float32)))
    assert np.array_equal(read_npy(tmp_path / "plain.npy", "path"), array)
    assert np.array_equal(read_npy(tmp_path / "fortran.npy", "path"), array)


def test_a_text_file_named_npy_is_reported_as_not_a_npy_file(tmp_path):
    np.savetxt(tmp_path / "text.npy", np.ones((2, 2)))
    with pytest.raises(ValueError, match=r"--map '.*text\.npy' is not a \.npy file: it starts with b'1\.0"):
        read_npy(tmp_path / "text.npy", "--map")
    with pytest.raises(ValueError, match=r"--map '.*missing\.npy' cannot be read"):
        read_npy(tmp_path / "missing.npy", "--map")


def test_sixteen_bit_png_keeps_its_values_for_the_pairs_and_the_command(tmp_path, capsys):
    from PIL import Image

    from enmi_torch.utils.files import read_image

    values = np.random.default_rng(3).integers(0, 65536, (16, 16)).astype(np.uint16)  # beyond 8 bits
    Image.fromarray(values).save(tmp_path / "deep.png")
    np.testing.assert_array_equal(read_image(tmp_path / "deep.png", "--map"), values)
    Image.fromarray(np.zeros((4, 4, 3), dtype=np.uint8)).save(tmp_path / "colour.png")
    with pytest.raises(ValueError, match=r"--map '.*colour\.png' is not a readable image: .*single-channel"):
        read_image(tmp_path / "colour.png", "--map")
    local = values[4:12, 5:13].astype(np.float32)
    np.save(tmp_path / "local.npy", local)
    main(
        [
            "--map",
            str(tmp_path / "deep.png"),
            "--local",
            str(tmp_path / "local.npy"),
            "--value-range",
            "0",
            "65536",
            "--shifts",
            "2",
            "--around",
            "9",
            "8",
            "--metric",
            "ncc",
        ]
    )
    report = json.loads(capsys.readouterr().out)
    assert (round(report["dx"]), round(report["dy"])) == (0, 0)


def test_a_complex_map_is_refused(tmp_path):
    np.save(tmp_path / "map.npy", np.ones((4, 4), dtype=np.complex64))
    with pytest.raises(ValueError, match=r"--map '.*map\.npy' must hold real values, got complex dtype complex64"):
        read_image(tmp_path / "map.npy", "--map")


def test_a_folder_where_a_mask_file_goes_is_named_by_the_argument(tmp_path):
    mask = LearnedVariance((4, 6))
    (tmp_path / "x.pt").mkdir()
    with pytest.raises(ValueError, match=r"^path must name a file to write, got the existing folder '.*x\.pt'$"):
        mask.save(tmp_path / "x.pt")
    (tmp_path / "notes").write_text("a file")
    with pytest.raises(
        ValueError, match=r"^path '.*notes/mask\.pt' cannot be written: '.*notes' on its path is a file$"
    ):
        mask.save(tmp_path / "notes" / "mask.pt")
    assert mask.save(tmp_path / "new" / "mask.pt").is_file()  # a folder that does not exist yet is made


def test_files_and_folders_to_write_are_told_apart(tmp_path):
    (tmp_path / "file").write_text("a file")
    with pytest.raises(ValueError, match=r"^--out must be a folder, got '.*file', which is a file$"):
        check_folder_to_write(tmp_path / "file", "--out")
    with pytest.raises(
        ValueError, match=r"^--out must be a folder, got '.*file/sub', but '.*file' on its path is a file"
    ):
        check_folder_to_write(tmp_path / "file" / "sub", "--out")
    assert check_folder_to_write(tmp_path / "new" / "sub", "--out") == tmp_path / "new" / "sub"
    assert check_file_to_write(tmp_path / "new" / "mask.npy", "path") == tmp_path / "new" / "mask.npy"
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if not os.access(locked, os.W_OK):  # root writes anywhere
            with pytest.raises(ValueError, match="is read-only"):
                check_folder_to_write(locked / "out", "--out")
            with pytest.raises(ValueError, match="is read-only"):
                check_file_to_write(locked / "mask.pt", "path")
    finally:
        locked.chmod(0o700)
