"""Issue 23, items 3, 5 and 6: commands, files and messages that named nothing or misled."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from enmi_torch import ECR, Localization, NoCandidateError, ecr, enmi, localize, ncc, nmi, nmi_from_joint_histogram
from enmi_torch.cli.localize import main as localize_main
from enmi_torch.utils.files import read_image


def _scene():
    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(1, 1, 48, 48, generator=generator) * 256
    return reference[..., 14:30, 19:35].clone(), reference


def test_an_off_map_window_is_told_it_lies_off_the_map():
    captured, reference = _scene()
    with pytest.raises(NoCandidateError, match=r"the search window lies off the map in sample\(s\) \[0\]"):
        localize(captured, reference, 64.0, score=ECR(bins=16), shifts=3, center=(500, 500))


def test_huge_yaws_are_refused_by_name_and_turns_are_taken_modulo_360():
    captured, reference = _scene()
    with pytest.raises(ValueError, match=r"yaws must be angles within \+-1e\+06 degrees .* got 1e\+300"):
        localize(captured, reference, 64.0, score=ECR(bins=16), shifts=3, yaws=[1e300])
    turned = localize(captured, reference, 64.0, score=ECR(bins=16), shifts=3, yaws=[-720.0, 5.0 - 720.0])
    assert turned.pose[0, :2].tolist() == [3.0, -2.0]


@pytest.mark.parametrize(
    ("yaws", "message"),
    [
        ("0:1e12:1", "gives 1e+12 yaws, more than the 36000 searched at most"),
        ("0:inf:1", "needs three finite numbers"),
    ],
)
def test_yaw_ranges_without_a_bound_end_in_one_line(capsys, yaws, message):
    with pytest.raises(SystemExit) as exit_info:
        localize_main(["--map", "map.npy", "--local", "local.npy", "--yaws", yaws])
    error = capsys.readouterr().err
    assert exit_info.value.code == 2 and error.count("\n") == 1 and message in error


def test_a_complex_map_is_refused(tmp_path):
    np.save(tmp_path / "map.npy", np.ones((4, 4), dtype=np.complex64))
    with pytest.raises(ValueError, match=r"--map '.*map\.npy' must hold real values, got complex dtype complex64"):
        read_image(tmp_path / "map.npy", "--map")


def test_local_to_map_names_a_wrong_center_or_shape():
    result = Localization(torch.tensor([[2.0, -1.0, 90.0]]), *(torch.zeros(1),) * 5)
    with pytest.raises(ValueError, match=r"center must be \(row, col\) or a \(1, 2\) tensor of them, got \(5,\)"):
        result.local_to_map((5,), (5, 5))
    with pytest.raises(ValueError, match=r"local_shape must be \(H, W\), two positive ints, got \(5,\)"):
        result.local_to_map((10, 20), (5,))


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda x: nmi(x, x.to("meta")), "reference must hold data, got a meta tensor"),
        (lambda x: nmi(x.to("meta"), x.to("meta")), "captured must hold data, got a meta tensor"),
        (lambda x: enmi(x, x.to("meta"), variance=4.0), "reference must hold data, got a meta tensor"),
        (lambda x: enmi(x, x, variance=torch.ones_like(x, device="meta")), "variance must hold data"),
        (lambda x: localize(x[..., :8, :8], x.to("meta"), 64.0, shifts=2), "reference must hold data"),
        (lambda x: ecr(x, x.to("meta"), 4.0), "reference must hold data, got a meta tensor"),
        (lambda x: ecr(x, x, torch.ones_like(x, device="meta")), "variance must hold data"),
        (lambda x: ncc(x, x.to("meta")), "reference must hold data, got a meta tensor"),
    ],
)
def test_a_reference_without_data_on_the_device_is_named(call, message):
    with pytest.raises(ValueError, match=message):
        call(torch.rand(1, 1, 16, 16) * 255)


def test_a_log_prior_that_rules_out_every_bin_is_refused():
    x = torch.rand(1, 1, 16, 16, generator=torch.Generator().manual_seed(0)) * 255
    with pytest.raises(ValueError, match="log_prior must allow at least one bin"):
        enmi(x, x + 1, variance=4.0, log_prior=torch.full((32,), -torch.inf))


@pytest.mark.parametrize("count", [float("nan"), -0.5, float("inf")])
def test_nmi_from_a_histogram_of_bad_counts_is_refused(count):
    counts = torch.ones(1, 4, 4)
    counts[0, 0, 0] = count
    with pytest.raises(ValueError, match="counts must be finite counts >= 0"):
        nmi_from_joint_histogram(counts)


@pytest.mark.parametrize(
    "call",
    [
        lambda x, r: nmi(x, r, value_range=(0.0, 1.0)),
        lambda x, r: enmi(x, r, variance=4.0, value_range=(0.0, 1.0)),
        lambda x, r: ecr(x, r, 4.0, value_range=(0.0, 1.0)),
    ],
)
def test_images_mostly_far_outside_value_range_are_refused(call):
    # 0-255 images against value_range=(0, 1), with a few pixels below 1 so that not all fall in one bin: the score
    # of the few pixels inside was returned (nmi gave 1.0006).
    generator = torch.Generator().manual_seed(3)
    captured = torch.rand(1, 1, 24, 20, generator=generator) * 255
    captured[..., :2, :] = torch.rand(1, 1, 2, 20, generator=generator)
    far = r"lies far outside value_range=\(0\.0, 1\.0\): [89]\d% of its valid pixels .* more than 8 range widths"
    with pytest.raises(
        ValueError,
        match=far,
    ):
        call(captured, captured.flip(-1))


def test_noise_spilling_past_value_range_is_still_scored():
    generator = torch.Generator().manual_seed(4)
    reference = torch.rand(1, 1, 24, 20, generator=generator, dtype=torch.float64) * 256
    # std 640: the paper's simulation at its largest noise power, on its farthest tiles
    captured = reference + 640.0 * torch.randn(reference.shape, generator=generator, dtype=torch.float64)
    assert ((captured < 0) | (captured > 256)).double().mean() > 0.7
    assert torch.isfinite(nmi(captured, reference)).all()


def test_float32_surfaces_refuse_values_whose_squares_overflow_and_float64_scores_them():
    from enmi_torch import ecr_surface

    captured, reference = _scene()
    captured[..., 3, 3] = 1e30  # one wild pixel: float32 squares overflowed into a NaN surface
    with pytest.raises(ValueError, match=r"captured holds 1 value\(s\) beyond \+-1e\+18 where captured_mask is True"):
        ecr_surface(captured, reference, 4.0, bins=16)
    with pytest.raises(ValueError, match=r"captured holds 1 value\(s\) beyond"):  # was 'no candidate passes'
        localize(captured, reference, 4.0, score=ECR(bins=16), shifts=3)
    surface = ecr_surface(captured.double(), reference.double(), 4.0, bins=16)
    assert torch.isfinite(surface.score).all()


@pytest.mark.parametrize(("scale", "variance", "shown"), [(1e-20, 4.0, "4e-40"), (1e19, 4.0, r"4e\+38")])
def test_a_variance_float32_cannot_hold_is_refused_and_float64_scores_it(scale, variance, shown):
    from enmi_torch import ecr_surface

    captured, reference = _scene()
    captured, reference = (captured * scale).double(), (reference * scale).double()
    options = {"bins": 16, "value_range": (0.0, 256 * scale)}
    wide = ecr_surface(captured, reference, variance * scale**2, **options)
    assert torch.isfinite(wide.score).all() and divmod(int(wide.score[0].argmax()), 33) == (14, 19)
    for given in (variance * scale**2, torch.full_like(captured, variance * scale**2)):
        with pytest.raises(ValueError, match=rf"variance must lie within 1.18e-38 to 3.4e\+35 .* got {shown}"):
            enmi(captured.float(), captured.float(), variance=given, value_range=options["value_range"])


def test_float32_ncc_of_a_wild_pixel_equals_float64():
    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
    captured = reference + 3 * torch.randn(1, 1, 16, 16, generator=generator)
    captured[..., 3, 3] = 1e30  # the squares overflowed float32: the score came out 0, float64 says 0.114
    expected = ncc(captured.double(), reference.double())
    assert 0.05 < float(expected) < 0.5
    torch.testing.assert_close(ncc(captured, reference), expected.float())
