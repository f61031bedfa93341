"""``PairDataModule``: local/prior pairs from a folder, or the embedded synthetic default, for Lightning."""

from __future__ import annotations

import math

import torch
from lightning.pytorch import LightningDataModule
from torch.utils.data import DataLoader, Dataset, DistributedSampler, Subset

from enmi_torch.data.pairs import PairDataset
from enmi_torch.data.resumable import ResumableLoader, ResumableSampler
from enmi_torch.data.synthetic import KeptPairs, SyntheticPairs, gravel_texture
from enmi_torch.data.truth import FLAVOURS, VarianceTruth, make_truth
from enmi_torch.utils.checks import check_non_negative_int, check_option, check_positive_int, check_positive_number


class ShardSampler(DistributedSampler):
    """Every ``num_replicas``-th index from ``rank``, in order, without the padding of :class:`DistributedSampler`.

    Each pair is visited exactly once over all processes, so sums over the shards equal one pass (statistics and
    held-out scores); being a :class:`DistributedSampler`, Lightning leaves it in place.
    """

    def __init__(self, dataset: Dataset, num_replicas: int, rank: int) -> None:
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=False)

    def __iter__(self):
        return iter(range(self.rank, len(self.dataset), self.num_replicas))

    def __len__(self) -> int:
        return len(range(self.rank, len(self.dataset), self.num_replicas))


class PairDataModule(LightningDataModule):
    """Pairs for fitting a variance mask: a folder in :mod:`enmi_torch.data.pairs` format, or synthetic pairs.

    Args:
        root: a folder of pairs; ``None`` (default) uses :class:`~enmi_torch.data.synthetic.SyntheticPairs`.
        flavour: synthetic noise field, ``"lidar"`` or ``"camera"`` (see :mod:`enmi_torch.data.truth`).
        train_pairs: number of synthetic training pairs.
        val_pairs: number of synthetic held-out pairs.
        size: side of the square synthetic images, in pixels (at most 512).
        noise_std: RMS noise std of the synthetic field over its valid pixels, in grey levels.
        gain_std: std of the synthetic per-pair intensity gain (0: none).
        offset_std: std of the synthetic per-pair intensity offset (0: none).
        val_fraction: share of a folder's pairs held out (a fixed draw from ``seed``).
        batch_size: pairs per optimisation step over all processes (split evenly between them).
        num_workers: data-loading worker processes per training process.
        seed: synthetic training pairs use seed ``2 * seed``, held-out ones ``2 * seed + 1``; shuffling uses ``seed``.
        keep_pairs: generate the synthetic pairs once, in :meth:`setup`, and keep them in memory
            (:class:`~enmi_torch.data.synthetic.KeptPairs`, ``9 H W`` bytes per pair); ``False`` draws each pair again
            whenever it is read. Either way every epoch sees the same pairs (pair ``i`` is a function of the seed and
            ``i``; only their order changes from epoch to epoch), so the fitted mask is the same, bit for bit;
            keeping them saves drawing every pair again each epoch (most of an epoch's time). A folder's pairs are
            always read from disk.

    Attributes:
        shape: ``(H, W)`` of the images.
        truth: the known noise field (synthetic data, or a folder whose ``meta.json`` names one), else ``None``.
    """

    def __init__(
        self,
        root: str | None = None,
        flavour: str = "lidar",
        train_pairs: int = 2000,
        val_pairs: int = 64,
        size: int = 128,
        noise_std: float = 12.0,
        gain_std: float = 0.0,
        offset_std: float = 0.0,
        val_fraction: float = 0.05,
        batch_size: int = 64,
        num_workers: int = 0,
        seed: int = 0,
        keep_pairs: bool = True,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.batch_size = check_positive_int("batch_size", batch_size)
        self.num_workers = check_non_negative_int("num_workers", num_workers)
        self.seed = check_non_negative_int("seed", seed)
        if not isinstance(keep_pairs, bool):
            raise TypeError(f"keep_pairs must be a bool, got {type(keep_pairs).__name__}")
        self.keep_pairs = keep_pairs
        self._train_loader: ResumableLoader | None = None
        self._train_loader_state: dict[str, int] | None = None  # from a checkpoint, for the next training loader
        # Checked for synthetic data too (where val_pairs holds out instead): a wrong value is never passed over.
        if not 0 < check_positive_number("val_fraction", val_fraction) < 1:
            raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
        if root is None:
            check_option("flavour", flavour, FLAVOURS)
            side = gravel_texture().shape[0]
            if check_positive_int("size", size) > side:
                raise ValueError(f"size must be at most {side} (the texture the pairs are cut from), got {size}")
            truth = make_truth(flavour, (size, size), noise_std)
            check_positive_int("train_pairs", train_pairs)
            check_positive_int("val_pairs", val_pairs)
            options = {"gain_std": gain_std, "offset_std": offset_std}
            self.train_set: Dataset = SyntheticPairs(truth, train_pairs, seed=2 * seed, **options)
            self.val_set: Dataset = SyntheticPairs(truth, val_pairs, seed=2 * seed + 1, **options)
            self.truth: VarianceTruth | None = truth
            self.shape = truth.shape
            return
        pairs = PairDataset(root)
        held_out = max(1, math.floor(val_fraction * len(pairs)))
        if held_out >= len(pairs):
            raise ValueError(f"{root} holds {len(pairs)} pair(s): too few to hold out {held_out} and train on the rest")
        order = torch.randperm(len(pairs), generator=torch.Generator().manual_seed(seed)).tolist()
        self.train_set = Subset(pairs, sorted(order[held_out:]))
        self.val_set = Subset(pairs, sorted(order[:held_out]))
        self.truth = pairs.truth
        self.shape = pairs.shape

    def setup(self, stage: str | None = None) -> None:
        """Generate the synthetic pairs once and keep them (``keep_pairs``), in every process."""
        if self.keep_pairs and isinstance(self.train_set, SyntheticPairs):
            self.train_set, self.val_set = KeptPairs(self.train_set), KeptPairs(self.val_set)

    @property
    def num_train_pairs(self) -> int:
        """Number of training pairs."""
        return len(self.train_set)

    def _world(self) -> tuple[int, int, int]:
        """``(world size, rank, per-process batch size)``."""
        trainer = self.trainer
        world, rank = (trainer.world_size, trainer.global_rank) if trainer is not None else (1, 0)
        if self.batch_size % world:
            raise ValueError(f"batch_size must be divisible by the number of processes {world}, got {self.batch_size}")
        return world, rank, self.batch_size // world

    def _loader(
        self, dataset: Dataset, sampler: DistributedSampler, batch_size: int, loader: type[DataLoader] = DataLoader
    ) -> DataLoader:
        return loader(
            dataset,
            batch_size=batch_size,
            sampler=sampler,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        """Shuffled each epoch by ``seed + epoch``; global batches are the same whatever the number of processes.

        A :class:`~enmi_torch.data.resumable.ResumableLoader`: a fit resumed from a checkpoint written mid-epoch goes
        on from the batch where it stopped.
        """
        world, rank, batch_size = self._world()
        sampler = ResumableSampler(self.train_set, num_replicas=world, rank=rank, shuffle=True, seed=self.seed)
        self._train_loader = self._loader(self.train_set, sampler, batch_size, ResumableLoader)
        if self._train_loader_state is not None:
            self._train_loader.load_state_dict(self._train_loader_state)
            self._train_loader_state = None
        return self._train_loader

    def state_dict(self) -> dict[str, dict[str, int]]:
        """The training loader's place in its epoch, saved in checkpoints.

        Lightning also saves the loader's own state, but restores it only if the training loader is built after the
        checkpoint's loops are loaded; a learning-rate schedule over ``estimated_stepping_batches`` builds it before.
        This state is restored earlier, with the data module's.
        """
        return {} if self._train_loader is None else {"train_loader": self._train_loader.state_dict()}

    def load_state_dict(self, state_dict: dict[str, dict[str, int]]) -> None:
        """Resume the next training loader where the checkpoint's stopped (see :meth:`state_dict`)."""
        if "train_loader" in state_dict:
            self._train_loader_state = state_dict["train_loader"]
            if self._train_loader is not None:
                self._train_loader.load_state_dict(self._train_loader_state)

    def val_dataloader(self) -> DataLoader:
        """Held-out pairs, each seen once over all processes."""
        world, rank, batch_size = self._world()
        return self._loader(self.val_set, ShardSampler(self.val_set, world, rank), batch_size)

    def statistics_dataloader(self) -> DataLoader:
        """Training pairs in order, each seen once over all processes (for the empirical mask)."""
        world, rank, batch_size = self._world()
        return self._loader(self.train_set, ShardSampler(self.train_set, world, rank), batch_size)
