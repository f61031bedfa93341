"""A training loader that resumes part-way through an epoch on the batch where it stopped.

Lightning saves the ``state_dict`` of a loader that has one in every checkpoint and hands it back on resume
(its stateful-loader protocol). :class:`ResumableLoader`'s state is the epoch and the number of batches it has
given in it; after ``load_state_dict`` its next pass over that epoch skips those batches, so a fit stopped
mid-epoch (a preemption checkpoint every N steps, SIGTERM) and resumed sees the batches an uninterrupted fit sees.
Without it Lightning restarts the epoch's loader from its first batch.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from torch.utils.data import DataLoader, DistributedSampler


class ResumableSampler(DistributedSampler):
    """:class:`DistributedSampler` whose next pass leaves out its first ``skip`` indices (then ``skip`` is 0 again).

    Its length stays the full epoch's: Lightning counts the epoch's batches from it.
    """

    skip: int = 0

    def __iter__(self) -> Iterator[int]:
        indices = list(super().__iter__())
        skip, self.skip = self.skip, 0
        return iter(indices[skip:])


class ResumableLoader(DataLoader):
    """A :class:`DataLoader` over a :class:`ResumableSampler` with Lightning's ``state_dict``/``load_state_dict``.

    ``state_dict()`` is ``{"epoch": e, "batches": n}``: ``n`` batches of epoch ``e`` given so far. A loaded state
    applies to the next pass if that pass is epoch ``e`` and ``n`` is short of the epoch (a checkpoint written at an
    epoch's end resumes on the next epoch's first batch).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if not isinstance(self.sampler, ResumableSampler):
            raise TypeError(f"sampler must be a ResumableSampler, got {type(self.sampler).__name__}")
        self._epoch = self.sampler.epoch
        self._given = 0
        self._to_skip: dict[str, int] | None = None

    def __iter__(self) -> Iterator[Any]:
        return self._batches()

    def _batches(self) -> Iterator[Any]:
        # A generator: this runs at the first batch, after Lightning has set the sampler's epoch.
        skip = self._to_skip
        self._to_skip = None
        self._epoch, self._given = self.sampler.epoch, 0
        if skip is not None and skip["epoch"] == self._epoch and 0 < skip["batches"] < len(self):
            self.sampler.skip = skip["batches"] * self.batch_size
            self._given = skip["batches"]
        for batch in super().__iter__():
            self._given += 1
            yield batch

    def state_dict(self) -> dict[str, int]:
        """The epoch and the number of its batches given so far."""
        return {"epoch": int(self._epoch), "batches": int(self._given)}

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Skip ``state["batches"]`` batches on the next pass, if that pass is epoch ``state["epoch"]``."""
        if not isinstance(state, dict) or set(state) != {"epoch", "batches"}:
            raise ValueError(f"a ResumableLoader state must be {{'epoch': int, 'batches': int}}, got {state!r}")
        self._to_skip = {"epoch": int(state["epoch"]), "batches": int(state["batches"])}
