"""A share of a list of work items: ``--shard i/n`` of dataset generation.

Without JAX (the command line parses ``--shard`` before importing it). A generator that
makes item ``i`` from its spec alone runs only ``Shard.select(specs)`` (or the ``i`` with
``Shard.owns(i)``); :mod:`diffgns.io.shards` writes and merges the files.
"""
from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence
from typing import TypeVar

from diffgns.errors import InputError

T = TypeVar("T")


@dataclasses.dataclass(frozen=True)
class Shard:
    """Shard ``index`` of ``count``: the items ``index, index + count, index + 2 count, ...``
    of a list of per-sample specs (round robin, so shards of a grid sorted by cost get
    equal shares)."""

    index: int = 0
    count: int = 1

    def __post_init__(self) -> None:
        if self.count < 1 or not 0 <= self.index < self.count:
            raise InputError("--shard", f"{self.index}/{self.count} is not a shard: needs "
                             "0 <= i < n", "give i/n with n >= 1 and i in 0 .. n-1, e.g. 0/2")

    @classmethod
    def parse(cls, text: str) -> Shard:
        """``"i/n"`` -> Shard(i, n); a one-line :class:`InputError` for anything else."""
        m = re.fullmatch(r"\s*(-?\d+)\s*/\s*(-?\d+)\s*", str(text))
        if not m:
            raise InputError("--shard", f"{text!r} is not i/n",
                             "give two integers, e.g. --shard 0/2 for the first of two")
        return cls(int(m.group(1)), int(m.group(2)))

    @classmethod
    def of_process(cls) -> Shard:
        """This process's shard of a multi-process run (``Shard(0, 1)`` in one process)."""
        import jax

        return cls(jax.process_index(), jax.process_count())

    def owns(self, i: int) -> bool:
        """Whether item ``i`` of the list belongs to this shard."""
        return i % self.count == self.index

    def indices(self, n: int) -> list[int]:
        """The positions in ``range(n)`` this shard owns."""
        return list(range(self.index, n, self.count))

    def select(self, items: Sequence[T]) -> list[T]:
        """The items this shard owns, in order."""
        return [items[i] for i in self.indices(len(items))]

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"
