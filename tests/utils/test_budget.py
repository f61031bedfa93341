"""The memory budget: calls whose sizes follow from their arguments refuse, before allocating, what exceeds it."""

import math

import pytest
import torch

from enmi_torch import ENMILoss, NMILoss, histogram
from enmi_torch.functional import enmi, enmi_surface, joint_histogram, ncc_surface, nmi, nmi_surface
from enmi_torch.histogram import hard_entropies
from enmi_torch.information import nmi_from_joint_histogram
from enmi_torch.localization.search import Localizer, localize
from enmi_torch.localization.strategy import SearchStrategy
from enmi_torch.utils import budget as _budget
from enmi_torch.utils.budget import MemoryBudgetError, get_memory_budget, memory_budget, set_memory_budget

GENERATOR = torch.Generator().manual_seed(15)
CAPTURED = torch.rand(1, 1, 16, 16, generator=GENERATOR) * 256
REFERENCE = torch.rand(1, 1, 16, 16, generator=GENERATOR) * 256
DEFAULT = _budget.DEFAULT_MEMORY_BUDGET
HUGE_BINS = r"bins=100000 needs about \d+\.\d GiB for the joint histograms \(1, 100000, 100000\) in float32"
RAISE_IT = r"raise the budget with enmi_torch\.utils\.budget\.set_memory_budget\(bytes\)"


@pytest.fixture(autouse=True)
def _default_budget():
    with memory_budget(DEFAULT):  # whatever ENMI_TORCH_MEMORY_BUDGET says
        yield


@pytest.mark.parametrize(
    "call",
    [
        lambda: nmi(CAPTURED, REFERENCE, bins=100000, kernel="triangular"),
        lambda: enmi(CAPTURED, REFERENCE, 4.0, bins=100000),
        lambda: enmi(CAPTURED, REFERENCE, torch.full((16, 16), 4.0), bins=100000),
        lambda: ENMILoss(bins=100000)(CAPTURED, REFERENCE, variance=4.0),
        lambda: NMILoss(bins=100000)(CAPTURED, REFERENCE),
        lambda: joint_histogram(CAPTURED, REFERENCE, bins=100000),
        lambda: joint_histogram(CAPTURED, REFERENCE, bins=100000, captured_variance=4.0),
    ],
    ids=["nmi-soft", "enmi", "enmi-map", "ENMILoss", "NMILoss", "joint_histogram", "joint_histogram-variance"],
)
def test_huge_bins_are_refused_before_allocating(call):
    with pytest.raises(MemoryBudgetError, match=f"^{HUGE_BINS}.*over the memory budget of 4.0 GiB.*{RAISE_IT}"):
        call()


def test_hard_nmi_with_huge_bins_counts_the_pixels_instead():
    """Hard NMI reads cell counts at the pixels: sorting them needs no bins^2 table, so it is exact and cheap."""
    captured = torch.arange(256.0).reshape(1, 1, 16, 16) + 0.5
    reference = (captured / 2).floor() * 2 + 0.5  # pairs of captured values share a reference value
    score = nmi(captured, reference, bins=100000, kernel="hard")
    assert score.item() == pytest.approx(1 + math.log(128) / math.log(256), abs=1e-6)
    assert nmi(CAPTURED, REFERENCE, bins=100000, kernel="hard").shape == (1,)
    with pytest.raises(ValueError, match=r"^bins must be at most 16777216 \(2\*\*24\), got 33554432"):
        nmi(CAPTURED, REFERENCE, bins=2**25)


def test_sorted_cell_counts_equal_the_table(monkeypatch):
    generator = torch.Generator().manual_seed(3)
    captured = torch.rand(3, 1, 6, 5, generator=generator) * 256
    candidates = torch.rand(4, 3, 1, 6, 5, generator=generator) * 256
    valid = torch.rand(3, 1, 6, 5, generator=generator) > 0.3
    tabled = hard_entropies(captured, candidates, bins=48, valid_mask=valid)
    monkeypatch.setattr(histogram, "_TABLE_CELLS", 0)  # every table is now too large: sort
    sorted_ = hard_entropies(captured, candidates, bins=48, valid_mask=valid)
    for table, sort in zip(tabled, sorted_, strict=True):
        assert torch.equal(table, sort)
    counts = joint_histogram(captured, candidates, bins=48, valid_mask=valid)
    torch.testing.assert_close(
        nmi(captured, candidates, bins=48, valid_mask=valid, kernel="hard"), nmi_from_joint_histogram(counts)
    )


def test_localize_refuses_a_huge_search_window():
    local, prior_map = CAPTURED / 256, torch.rand(1, 1, 64, 64, generator=GENERATOR)
    with pytest.raises(
        MemoryBudgetError, match=rf"^shifts=10000 needs about .* 20016 x 20016 search window.*{RAISE_IT}"
    ):
        localize(local, prior_map, 25.0, shifts=10**4)
    with pytest.raises(MemoryBudgetError, match=r"^shifts=\(10000, 10000\) with coarse_factor=2 needs about .* GiB"):
        Localizer(score="ncc", shifts=10**4, search=SearchStrategy(coarse_factor=2))(local, prior_map)


def test_surfaces_refuse_a_huge_window():
    local, window = CAPTURED[..., :8, :8], torch.rand(1, 1, 64, 64, generator=GENERATOR) * 256
    with memory_budget(1 << 20):
        with pytest.raises(MemoryBudgetError, match=r"^a 64 x 64 window with bins=32 needs about .* MiB for the FFT"):
            enmi_surface(local, window, 4.0)
        with pytest.raises(MemoryBudgetError, match="a 64 x 64 window with bins=32 needs"):
            nmi_surface(local, window, kernel="hard")
    with memory_budget(100_000), pytest.raises(MemoryBudgetError, match=r"window needs .*: pass a smaller window, or"):
        ncc_surface(local, window)
    assert nmi_surface(local, window, kernel="hard").score.shape == (1, 57, 57)


def test_the_budget_can_be_raised_lowered_and_turned_off():
    assert get_memory_budget() == DEFAULT
    with memory_budget(10_000):
        assert get_memory_budget() == 10_000
        with pytest.raises(MemoryBudgetError, match=r"bins=64 needs about 16.0 KiB .* budget of 9.8 KiB"):
            joint_histogram(CAPTURED, REFERENCE, bins=64)
        with memory_budget(None):
            assert joint_histogram(CAPTURED, REFERENCE, bins=64).shape == (1, 64, 64)
    assert get_memory_budget() == DEFAULT
    previous = set_memory_budget(2e9)
    try:
        assert previous == DEFAULT and get_memory_budget() == 2_000_000_000
    finally:
        set_memory_budget(previous)
    assert isinstance(MemoryBudgetError("x"), ValueError)


@pytest.mark.parametrize("budget", [0, -1, math.inf, math.nan, "4GB", True])
def test_invalid_budgets_are_refused(budget):
    with pytest.raises(ValueError, match=r"budget must be a number of bytes > 0 or None, got"):
        set_memory_budget(budget)
    assert get_memory_budget() == DEFAULT


@pytest.mark.parametrize(("text", "budget"), [(None, DEFAULT), ("16e9", 16_000_000_000), ("None", None)])
def test_the_budget_comes_from_the_environment(monkeypatch, text, budget):
    if text is None:
        monkeypatch.delenv("ENMI_TORCH_MEMORY_BUDGET", raising=False)
    else:
        monkeypatch.setenv("ENMI_TORCH_MEMORY_BUDGET", text)
    assert _budget._budget_from_environment() == budget


def test_a_bad_environment_budget_is_named(monkeypatch):
    monkeypatch.setenv("ENMI_TORCH_MEMORY_BUDGET", "lots")
    with pytest.raises(
        ValueError, match="ENMI_TORCH_MEMORY_BUDGET must be a number of bytes > 0 or 'none', got 'lots'"
    ):
        _budget._budget_from_environment()


@pytest.mark.parametrize("kernel", ["hard", "mass"])
def test_the_histogram_estimate_is_the_size_of_the_counts(kernel):
    variance = 4.0 if kernel == "mass" else None
    counts = joint_histogram(CAPTURED, REFERENCE, bins=40, captured_variance=variance, kernel=kernel)
    estimate = _budget.joint_histogram_bytes(1, 1, 256, 40, 4, captured_planes=False, reference_planes=False)
    assert estimate == counts.numel() * counts.element_size()


def test_format_bytes():
    assert [_budget.format_bytes(count) for count in (512, 1536, 80e9, 2**50)] == [
        "512 bytes",
        "1.5 KiB",
        "74.5 GiB",
        "1024.0 TiB",
    ]


def test_a_score_counts_the_entropies_of_its_histograms_and_a_bare_histogram_does_not():
    # The scores hold three more tensors of the histograms' size for the entropies: a smaller budget refuses them.
    with pytest.raises(MemoryBudgetError, match=r"in float32, their entropies and the bin weights of 256 pixels"):
        nmi(CAPTURED, REFERENCE, bins=100000, kernel="triangular")
    with pytest.raises(MemoryBudgetError, match=r"\(1, 100000, 100000\) in float32 and their entropies, over"):
        enmi(CAPTURED, REFERENCE, 4.0, bins=100000)
    with pytest.raises(MemoryBudgetError, match=r"\(1, 100000, 100000\) in float32, over the memory budget"):
        joint_histogram(CAPTURED, REFERENCE, bins=100000, captured_variance=4.0)
    histogram_bytes = 4 * 2000 * 2000
    with memory_budget(2 * histogram_bytes):  # one histogram fits, four do not
        assert joint_histogram(CAPTURED, REFERENCE, bins=2000, captured_variance=4.0).shape == (1, 2000, 2000)
        with pytest.raises(MemoryBudgetError, match="their entropies"):
            enmi(CAPTURED, REFERENCE, 4.0, bins=2000)
