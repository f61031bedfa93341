import json
from pathlib import Path

import numpy as np
import pytest
import torch

from data_tools.experiments.mask import scene_change_pairs
from enmi_torch.data.pairs import PairDataset


@pytest.fixture(scope="module")
def pairs_tool():
    return scene_change_pairs


def _real_folders(root: Path) -> None:
    """Three pair folders of one dataset whose captured image is the inverted reference."""
    generator = np.random.default_rng(0)
    for index in range(3):
        folder = root / "another-date" / f"survey-{index}"
        folder.mkdir(parents=True)
        reference = generator.uniform(0, 255, (70, 90)).astype(np.float32)
        np.save(folder / "reference.npy", reference)
        np.save(folder / "captured.npy", 255 - reference)


def test_real_pairs_are_co_registered_crops_of_the_chosen_half_plus_the_sensor_noise(pairs_tool, tmp_path):
    _real_folders(tmp_path / "data")
    output = tmp_path / "pairs"
    argv = [
        "--pairs",
        "6",
        "--sources",
        "real:another-date/survey",
        "--level",
        "0.001",
        "--data",
        str(tmp_path / "data"),
    ]
    pairs_tool.main([str(output), *argv])
    dataset = PairDataset(output)
    assert len(dataset) == 6 and dataset.shape == (64, 64)
    for index in range(6):
        item = dataset[index]
        torch.testing.assert_close(item["local"], 255 - item["prior"], atol=0.02, rtol=0)
    meta = json.loads(json.loads((output / "meta.json").read_text())["source"])
    used = [Path(folder).name for folder in meta["real_folders_used"]["real:another-date/survey"]]
    assert used == ["survey-0", "survey-2"] and meta["real_folders"] == "even"


def test_controlled_pairs_change_the_scene_and_carry_the_sensors_variance(pairs_tool, tmp_path):
    pairs, truth, used = pairs_tool.make_pairs(["controlled"], 12, "camera-like", 50.0, (1.0, 1.0), 3, None, "even")
    again, _, _ = pairs_tool.make_pairs(["controlled"], 12, "camera-like", 50.0, (1.0, 1.0), 3, None, "even")
    assert used == {} and all(torch.equal(a["local"], b["local"]) for a, b in zip(pairs, again, strict=True))
    unit, _ = pairs_tool.YARDSTICK.NOISE_ONLY.variance_profile("camera-like")
    torch.testing.assert_close(truth.variance, 2500.0 * unit)
    residual = torch.stack([pair["local"] - pair["prior"] for pair in pairs]).double()
    # The far rows' noise dominates there; on the near rows (variance ~25) the scene change shows.
    far, near = residual[:, :8].var(), residual[:, -8:].var()
    assert float(far) > 0.8 * float(truth.variance[:8].mean())
    assert float(near) > 4 * float(truth.variance[-8:].mean())


def test_paper_camera_pairs_leave_the_unseen_cells_out(pairs_tool):
    pairs, truth, _ = pairs_tool.make_pairs(["controlled"], 2, "paper-camera", 30.0, (0.5, 0.5), 0, None, "even")
    assert not bool(truth.valid.all()) and torch.equal(pairs[0]["valid"], truth.valid)
    assert bool((pairs[0]["local"][~truth.valid] == 0).all())


def test_mistakes_exit_with_2(pairs_tool, tmp_path, capsys):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "file").write_text("x")
    for argv in (
        [str(tmp_path / "full")],
        [str(tmp_path / "new"), "--sources", "fog"],
        [str(tmp_path / "new"), "--strength", "0.5", "0.2"],
        [str(tmp_path / "new"), "--sources", "real:another-date/none", "--data", str(tmp_path)],
    ):
        with pytest.raises(SystemExit) as exit_info:
            pairs_tool.main(argv)
        assert exit_info.value.code == 2
    assert "sources" in capsys.readouterr().err
