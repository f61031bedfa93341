from types import SimpleNamespace

import pytest
import torch

from enmi_torch.data import (
    KeptPairs,
    PairDataModule,
    PairDataset,
    ShardSampler,
    SyntheticPairs,
    lidar_truth,
    write_pairs,
)


def global_batches(module, world):
    """The indices of every optimisation step, gathered over ``world`` simulated processes."""
    per_rank = []
    for rank in range(world):
        module.trainer = SimpleNamespace(world_size=world, global_rank=rank)
        loader = module.train_dataloader()
        loader.sampler.set_epoch(3)
        per_rank.append([batch["index"].tolist() for batch in loader])
    return [sorted(index for batches in per_rank for index in batches[step]) for step in range(len(per_rank[0]))]


def test_synthetic_module_shapes_and_truth():
    module = PairDataModule(train_pairs=20, val_pairs=6, size=16, batch_size=4)
    assert module.shape == (16, 16) and module.truth is not None and module.num_train_pairs == 20
    batch = next(iter(module.train_dataloader()))
    assert batch["local"].shape == (4, 1, 16, 16) and batch["valid"].dtype == torch.bool
    assert len(module.val_set) == 6
    assert not torch.equal(module.train_set[0]["prior"], module.val_set[0]["prior"])


def all_batches(module, epochs=(0, 1)):
    """Every batch of the training loader at these epochs, of the statistics and of the validation loaders."""
    batches = []
    for epoch in epochs:
        loader = module.train_dataloader()
        loader.sampler.set_epoch(epoch)
        batches += list(loader)
    return batches + list(module.statistics_dataloader()) + list(module.val_dataloader())


def test_kept_pairs_give_the_batches_of_pairs_drawn_every_epoch():
    options = {"train_pairs": 20, "val_pairs": 6, "size": 16, "batch_size": 8, "gain_std": 0.1, "offset_std": 2.0}
    kept, drawn = PairDataModule(**options), PairDataModule(**options, keep_pairs=False)
    kept.setup("fit")
    drawn.setup("fit")
    assert isinstance(kept.train_set, KeptPairs) and isinstance(kept.val_set, KeptPairs)
    assert isinstance(drawn.train_set, SyntheticPairs)
    first, second = all_batches(kept), all_batches(drawn)
    assert len(first) == len(second) == 2 * 3 + 3 + 1
    for mine, theirs in zip(first, second, strict=True):
        assert mine.keys() == theirs.keys()
        assert all(torch.equal(mine[key], theirs[key]) for key in mine)
    # The epochs differ only in order: the same pairs, shuffled again.
    epoch_0, epoch_1 = (torch.cat([batch["index"] for batch in first[start : start + 3]]) for start in (0, 3))
    assert not torch.equal(epoch_0, epoch_1) and torch.equal(epoch_0.sort().values, epoch_1.sort().values)


def test_global_batches_do_not_depend_on_the_number_of_processes():
    module = PairDataModule(train_pairs=24, val_pairs=2, size=8, batch_size=6)
    one = global_batches(module, 1)
    two = global_batches(module, 2)
    assert [sorted(step) for step in one] == two
    assert sorted(index for step in one for index in step) == list(range(24))


@pytest.mark.parametrize("world", [1, 2, 3])
def test_shard_sampler_visits_every_index_once(world):
    dataset = list(range(10))
    seen = sorted(index for rank in range(world) for index in ShardSampler(dataset, world, rank))
    assert seen == list(range(10))
    assert sum(len(ShardSampler(dataset, world, rank)) for rank in range(world)) == 10


def test_folder_split_is_disjoint_and_seeded(tmp_path):
    truth = lidar_truth((8, 8))
    write_pairs(tmp_path / "pairs", SyntheticPairs(truth, 20), truth=truth)
    module = PairDataModule(root=str(tmp_path / "pairs"), val_fraction=0.25, batch_size=5)
    again = PairDataModule(root=str(tmp_path / "pairs"), val_fraction=0.25, batch_size=5)
    assert len(module.val_set) == 5 and module.num_train_pairs == 15
    assert set(module.val_set.indices).isdisjoint(module.train_set.indices)
    assert module.val_set.indices == again.val_set.indices
    assert module.shape == (8, 8) and module.truth is not None
    module.setup("fit")
    assert isinstance(module.train_set.dataset, PairDataset)  # a folder is read from disk, not kept
    statistics = [batch["index"] for batch in module.statistics_dataloader()]
    assert sorted(torch.cat(statistics).tolist()) == sorted(module.train_set.indices)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda tmp: PairDataModule(flavour="sonar"), "flavour must be one of"),
        (lambda tmp: PairDataModule(size=0), "size"),
        (lambda tmp: PairDataModule(batch_size=0), "batch_size"),
        (lambda tmp: PairDataModule(root=str(tmp), val_fraction=1.5), "val_fraction"),
        (lambda tmp: PairDataModule(root=str(tmp / "none")), "root must be a folder"),
        (lambda tmp: PairDataModule(keep_pairs="yes"), "keep_pairs must be a bool"),
    ],
)
def test_invalid_inputs(tmp_path, make, match):
    with pytest.raises((ValueError, FileNotFoundError, TypeError), match=match):
        make(tmp_path)


def test_batch_size_must_split_over_processes():
    module = PairDataModule(train_pairs=8, val_pairs=2, size=8, batch_size=5)
    module.trainer = SimpleNamespace(world_size=2, global_rank=0)
    with pytest.raises(ValueError, match="divisible by the number of processes 2"):
        module.train_dataloader()
