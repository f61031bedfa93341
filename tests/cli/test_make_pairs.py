import pytest
import torch

from enmi_torch.cli.make_pairs import main
from enmi_torch.data import PairDataset, SyntheticPairs, make_truth


def test_writes_a_pair_folder_equal_to_the_synthetic_pairs(tmp_path, capsys):
    main([str(tmp_path / "pairs"), "--pairs", "3", "--size", "16", "--flavour", "camera", "--seed", "2"])
    assert "wrote 3 camera-like pairs of 16x16" in capsys.readouterr().out
    dataset = PairDataset(tmp_path / "pairs")
    expected = SyntheticPairs(make_truth("camera", (16, 16), 12.0), 3, seed=2)
    for index in range(3):
        assert torch.equal(dataset[index]["local"], expected[index]["local"])
    torch.testing.assert_close(dataset.truth.variance, expected.truth.variance, equal_nan=True)


def test_refuses_a_folder_with_files_in_one_line(tmp_path, capsys):
    (tmp_path / "taken.txt").write_text("x")
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path), "--pairs", "1"])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.startswith("enmi-make-pairs: error: OUT must be a new or empty folder")


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--size", "600"], "--size must be from 1 to 512"),
        (["--pairs", "0"], "--pairs must be an int >= 1, got 0"),
        (["--noise-std", "-1"], "--noise-std must be a finite number > 0, got -1.0"),
        (["--noise-std", "1e300"], "--noise-std must be at most 1e+14 (the pairs are float32"),  # was an OverflowError
        (["--gain-std", "1e300"], "--gain-std must be at most 1e+14 (the pairs are float32 images"),  # inf pixels
        (["--offset-std", "inf"], "--offset-std must be a finite number >= 0, got inf"),
    ],
)
def test_mistakes_name_the_flag_typed(tmp_path, capsys, arguments, message):
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path / "pairs"), *arguments])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.startswith(f"enmi-make-pairs: error: {message}"), error
