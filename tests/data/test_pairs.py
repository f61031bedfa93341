import json

import numpy as np
import pytest
import torch
from PIL import Image

from enmi_torch.data import PairDataset, SyntheticPairs, lidar_truth, write_pairs


@pytest.fixture
def truth():
    return lidar_truth((12, 10))


@pytest.fixture
def folder(tmp_path, truth):
    root = tmp_path / "pairs"
    write_pairs(root, SyntheticPairs(truth, 6, seed=1), truth=truth, source="test")
    return root


def test_npy_round_trip(folder, truth):
    dataset = PairDataset(folder)
    source = SyntheticPairs(truth, 6, seed=1)
    assert len(dataset) == 6 and dataset.shape == (12, 10) and dataset.names[0] == "000000"
    for index in range(6):
        for key in ("local", "prior", "valid"):
            assert torch.equal(dataset[index][key], source[index][key])
    torch.testing.assert_close(dataset.truth.variance, truth.variance, equal_nan=True)
    assert torch.equal(dataset.truth.valid, truth.valid)
    assert json.loads((folder / "meta.json").read_text())["source"] == "test"


def test_png_round_trip_is_quantised(tmp_path, truth):
    root = tmp_path / "png"
    source = SyntheticPairs(truth, 3, seed=1)
    write_pairs(root, source, image_format="png")
    dataset = PairDataset(root)
    for index in range(3):
        expected = source[index]["local"].clamp(0, 255)
        assert (dataset[index]["local"] - expected).abs().max() <= 0.5
        assert torch.equal(dataset[index]["valid"], source[index]["valid"])
    assert dataset.truth is None


def test_without_meta_or_valid_the_shape_comes_from_the_images(folder):
    (folder / "meta.json").unlink()
    for path in (folder / "valid").iterdir():
        path.unlink()
    (folder / "valid").rmdir()
    dataset = PairDataset(folder)
    assert dataset.shape == (12, 10) and dataset.truth is None and bool(dataset[0]["valid"].all())


def test_images_are_read_lazily(folder):
    (folder / "local" / "000004.npy").write_bytes(b"garbage")
    dataset = PairDataset(folder)
    dataset[0]
    with pytest.raises(ValueError, match=r"local/000004\.npy' is not a \.npy file"):
        dataset[4]


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda root: (root / "prior" / "000002.npy").unlink(), r"local/000002\.npy has no partner in .*prior"),
        (lambda root: (root / "local" / "000003.npy").unlink(), r"prior/000003\.npy has no partner in .*local"),
        (lambda root: (root / "valid" / "000001.npy").unlink(), r"local/000001\.npy has no partner in .*valid"),
        (lambda root: (root / "local" / "000001.png").write_bytes(b""), r"000001\.npy and .*000001\.png"),
        (lambda root: (root / "meta.json").write_text("{not json"), r"meta\.json' is not readable JSON"),
        (
            lambda root: (root / "meta.json").write_bytes(b"\x80\xff"),
            r"meta\.json' is not readable JSON: it is not UTF-8",
        ),
        (
            lambda root: (root / "meta.json").write_text("[" * 100_000),
            r"meta\.json' is not readable JSON: it nests too",
        ),
        (lambda root: (root / "meta.json").write_text('{"format": "x"}'), r"meta\.json must be a JSON object"),
        (
            lambda root: (root / "meta.json").write_text(
                json.dumps({"format": "enmi_torch.pairs", "version": 1, "shape": 5})
            ),
            r"meta\.json shape must be \(H, W\), two positive ints, got 5",
        ),
        (lambda root: [path.unlink() for path in (root / "local").iterdir()], "holds no .npy or .png"),
    ],
)
def test_bad_folders_are_refused_at_construction(folder, damage, match):
    damage(folder)
    with pytest.raises(ValueError, match=match):
        PairDataset(folder)


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda root: np.save(root / "prior" / "000000.npy", np.zeros((12, 11))), r"prior/000000\.npy has shape"),
        (
            lambda root: np.save(root / "local" / "000000.npy", np.zeros((2, 12, 10))),
            r"local/000000\.npy' must hold a single-channel",
        ),
        (
            lambda root: np.save(root / "local" / "000000.npy", np.array([{}], dtype=object), allow_pickle=True),
            r"local/000000\.npy' is refused: it holds Python objects",
        ),
        (
            lambda root: (root / "local" / "000000.npy").write_text("1 2 3\n4 5 6\n"),
            r"local/000000\.npy' is not a \.npy file: it starts with b'1 2 3",
        ),
        (lambda root: np.save(root / "valid" / "000000.npy", np.ones((12, 10))), r"valid/000000\.npy must hold a bool"),
        (
            lambda root: np.save(root / "local" / "000000.npy", np.full((12, 10), np.nan, dtype=np.float32)),
            r"local/000000\.npy holds .* NaN",
        ),
    ],
)
def test_bad_files_are_named_when_read(folder, damage, match):
    damage(folder)
    with pytest.raises(ValueError, match=match):
        PairDataset(folder)[0]


def test_colour_png_is_refused(tmp_path, truth):
    root = tmp_path / "png"
    write_pairs(root, SyntheticPairs(truth, 1), image_format="png")
    Image.fromarray(np.zeros((12, 10, 3), dtype=np.uint8)).save(root / "prior" / "000000.png")
    with pytest.raises(ValueError, match=r"prior/000000\.png' .*single-channel"):
        PairDataset(root)[0]


def test_nan_outside_valid_is_allowed(folder):
    local = np.load(folder / "local" / "000000.npy")
    valid = np.load(folder / "valid" / "000000.npy")
    np.save(folder / "local" / "000000.npy", np.where(valid, local, np.nan).astype(np.float32))
    assert torch.isnan(PairDataset(folder)[0]["local"]).any()


def test_write_pairs_refuses_a_folder_with_files(folder, truth):
    with pytest.raises(ValueError, match="new or empty folder"):
        write_pairs(folder, SyntheticPairs(truth, 1))
    with pytest.raises(ValueError, match="image_format"):
        write_pairs(folder / "new", SyntheticPairs(truth, 1), image_format="jpg")
    with pytest.raises(FileNotFoundError, match="root must be a folder"):
        PairDataset(folder / "missing")
