"""The peak read-out: the sub-cell quadratic fit, the yaw parabola, separated peaks, the margin."""

import pytest
import torch

from enmi_torch.localization.peak import Localization, _parabola_offset, _quadratic_fit, _quadratic_peak


def test_subcell_peak_of_an_exact_quadratic_and_its_covariance():
    rows, cols = torch.meshgrid(torch.arange(7.0).double(), torch.arange(9.0).double(), indexing="ij")
    curvature = torch.tensor([[2.0, 0.6], [0.6, 1.2]], dtype=torch.float64)
    offset = torch.stack([cols - 4.3, rows - 2.8], dim=-1)
    plane = 5 - 0.5 * torch.einsum("...i,ij,...j->...", offset, curvature, offset)
    sub_cell, covariance = _quadratic_peak(plane, 3, 4)
    torch.testing.assert_close(sub_cell, torch.tensor([0.3, -0.2], dtype=torch.float64))
    torch.testing.assert_close(covariance, torch.linalg.inv(curvature))
    _, on_edge = _quadratic_peak(plane, 0, 4)
    assert torch.isinf(on_edge.diagonal()).all()


def test_subcell_fit_recentres_when_the_vertex_leaves_the_peak_cell():
    # An elongated quadratic whose grid maximum (row 4, col 3) is not the cell nearest its vertex (x 3.3, y 3.4).
    rows, cols = torch.meshgrid(torch.arange(7.0), torch.arange(8.0), indexing="ij")
    dx, dy = cols.double() - 3.3, rows.double() - 3.4
    plane = -(dx**2 + 1.8 * dx * dy + dy**2)
    assert divmod(int(plane.argmax()), 8) == (4, 3)
    offset, covariance = _quadratic_peak(plane, 4, 3)
    assert (3 + offset[0].item(), 4 + offset[1].item()) == pytest.approx((3.3, 3.4), abs=1e-9)
    torch.testing.assert_close(
        covariance, torch.linalg.inv(torch.tensor([[2.0, 1.8], [1.8, 2.0]], dtype=torch.float64))
    )


def test_a_subcell_fit_that_fails_is_reported_and_falls_back_to_the_parabola_along_each_axis():
    # Mutations killed: the fallback's axes swapped; no fallback (offset 0, the former behaviour).
    plane = torch.zeros(5, 5, dtype=torch.float64)
    plane[1:4, 1:4] = torch.tensor([[68.0, 75.0, 23.0], [81.0, 93.0, 20.0], [15.0, 48.0, 92.0]], dtype=torch.float64)
    offset, covariance = _quadratic_peak(plane, 2, 2)
    assert torch.isinf(covariance.diagonal()).all()

    def vertex(left, middle, right):  # the parabola through (-1, left), (0, middle), (1, right)
        return 0.5 * (left - right) / (left - 2 * middle + right)

    assert offset.tolist() == pytest.approx([vertex(81.0, 93.0, 20.0), vertex(75.0, 93.0, 48.0)])


def test_a_ridge_across_the_axes_is_read_by_the_parabolas_along_them():
    # A ridge along the diagonal falls barely along it: the 3 x 3 quadratic is no maximum (or its vertex runs off).
    rows, cols = torch.meshgrid(torch.arange(9.0).double(), torch.arange(9.0).double(), indexing="ij")
    along, across = (cols - 4.3 + rows - 3.8) / 2**0.5, (cols - 4.3 - rows + 3.8) / 2**0.5
    plane = -(across**2) / 0.5 - 0.001 * along**2 + 0.3 * along
    assert _quadratic_fit(plane, 4, 4) is None or bool((_quadratic_fit(plane, 4, 4)[0].abs() > 0.5).any())
    offset, covariance = _quadratic_peak(plane, 4, 4)
    assert torch.isinf(covariance.diagonal()).all()
    expected = [_parabola_offset(plane[4, 3:6]).item(), _parabola_offset(plane[3:6, 4]).item()]
    assert offset.tolist() == pytest.approx(expected) and expected[0] != 0 and expected[1] != 0


def test_parabola_offset_is_clamped_on_both_sides_and_zero_without_curvature():
    from enmi_torch.localization.peak import _parabola_offset

    assert _parabola_offset(torch.tensor([1.0, 1.0, 0.0])).item() == -0.5
    assert _parabola_offset(torch.tensor([0.0, 1.0, 1.0])).item() == 0.5
    assert _parabola_offset(torch.tensor([3.0, 2.0, 0.0])).item() == -0.5  # the vertex lies 1.5 steps left
    assert _parabola_offset(torch.tensor([0.0, 2.0, 3.0])).item() == 0.5
    assert _parabola_offset(torch.tensor([1.0, 1.0, 1.0])).item() == 0.0  # flat: no vertex


def test_separated_peaks_exclude_the_same_reach_on_every_side():
    from enmi_torch.localization.peak import separated_peaks

    surface = torch.zeros(1, 9, 11, dtype=torch.float64)
    surface[0, 4, 5] = 10.0
    # Each just outside a radius of 2 around the best one: left, right, up, down.
    for (row, col), value in {(4, 2): 6.0, (4, 8): 7.0, (1, 5): 8.0, (7, 5): 9.0}.items():
        surface[0, row, col] = value
    peaks = separated_peaks(surface, 5, 2)
    assert peaks == [(0, 4, 5), (0, 7, 5), (0, 1, 5), (0, 4, 8), (0, 4, 2)]


@pytest.mark.parametrize(("row", "col"), [(4, 8), (4, 2), (1, 5), (7, 5)])
def test_margin_looks_just_outside_the_exclusion_radius_on_every_side(row, col):
    from enmi_torch.localization.peak import read_peak

    rows, cols = torch.meshgrid(torch.arange(9.0), torch.arange(11.0), indexing="ij")
    surface = (-((rows - 4) ** 2) - (cols - 5) ** 2).double()[None, None] * 0.1 + 10.0  # one smooth peak
    surface[0, 0, row, col] = 9.9  # the runner-up, 3 cells away along one axis
    result = read_peak(surface, torch.zeros(1, dtype=torch.float64), (4, 5), exclusion_radius=2)
    assert result.margin.item() == pytest.approx(0.1)


@pytest.mark.parametrize("col", [0, 10])
def test_a_peak_on_the_left_or_right_edge_has_no_fit_and_only_the_parabola_along_the_edge(col):
    # No 3 x 3 fit and no parabola across the edge (x); along it (y) the parabola through the peak finds 4.3 exactly.
    from enmi_torch.localization.peak import _quadratic_peak

    rows, cols = torch.meshgrid(torch.arange(9.0).double(), torch.arange(11.0).double(), indexing="ij")
    plane = -((rows - 4.3) ** 2) - (cols - col) ** 2
    offset, covariance = _quadratic_peak(plane, 4, col)
    assert offset.tolist() == pytest.approx([0.0, 0.3]) and torch.isinf(covariance.diagonal()).all()


def test_local_to_map_names_a_wrong_center_or_shape():
    result = Localization(torch.tensor([[2.0, -1.0, 90.0]]), *(torch.zeros(1),) * 5)
    with pytest.raises(ValueError, match=r"local_shape must be \(H, W\), two positive ints, got \(5,\)"):
        result.local_to_map((5,))
    with pytest.warns(DeprecationWarning, match="local_to_map"), pytest.raises(ValueError, match=r"center must be"):
        result.local_to_map((5,), (5, 5))  # the former call, (center, local_shape)
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match=r"local_shape must be \(H, W\)"):
        result.local_to_map((10, 20), (5,))


def test_the_shift_is_the_pose_less_the_cell_searched_around_and_the_former_call_adds_it_to_center():
    # Mutations killed: shift as around - pose; the former local_to_map(center, shape) reading center as (x, y).
    pose = torch.tensor([[32.5, 17.25, 10.0], [5.0, 6.0, -3.0]], dtype=torch.float64)
    around = torch.tensor([[30.0, 20.0], [4.0, 9.0]], dtype=torch.float64)
    result = Localization(pose, *(torch.zeros(2),) * 5, around)
    assert result.shift.tolist() == [[2.5, -2.75], [1.0, -3.0]]
    assert result.dx.tolist() == [2.5, 1.0] and result.dy.tolist() == [-2.75, -3.0]
    assert Localization(pose, *(torch.zeros(2),) * 5).shift.tolist() == pose[:, :2].tolist()  # no around: origin
    with pytest.warns(DeprecationWarning):
        # Former code: the centre (row, col) it searched around plus the relative pose (now the shift).
        former = result.local_to_map(torch.tensor([[20, 30], [9, 4]]), (6, 8))
    torch.testing.assert_close(former, result.local_to_map((6, 8)))
