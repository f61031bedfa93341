import torch

from data_tools.make_pairs import main
from enmi_torch.data import PairDataset, SyntheticPairs, make_truth


def test_writes_a_pair_folder_equal_to_the_synthetic_pairs(tmp_path, capsys):
    main([str(tmp_path / "pairs"), "--pairs", "3", "--size", "16", "--flavour", "camera", "--seed", "2"])
    assert "wrote 3 camera-like pairs of 16x16" in capsys.readouterr().out
    dataset = PairDataset(tmp_path / "pairs")
    expected = SyntheticPairs(make_truth("camera", (16, 16), 12.0), 3, seed=2)
    for index in range(3):
        assert torch.equal(dataset[index]["local"], expected[index]["local"])
    torch.testing.assert_close(dataset.truth.variance, expected.truth.variance, equal_nan=True)
