"""A device's noise over a batch of benches: each bench draws from a generator of its own.

A bench's generator for a device is the world's seed spawned by the bench's name (its session's id, in the
simulated runner) and then by the device's name (``acquisition.devices.kinds.device_rng``). So a bench's
readings do not depend on which benches share its batch: a plan's session is the same simulated alone, in a
batch of 128, or in another process; and adding a device to a description changes no other device's draws.

Streams are column tables whose rows belong to benches (their ``robot`` column): :meth:`BenchNoise.rows`
gives the draws for such rows, each row's values from its bench's generator, in the row order of that bench.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from acquisition.devices.kinds import device_rng, spawned


class BenchNoise:
    """One device's generators, one per bench of a batch (``benches``: the benches' names; None: the world's
    seed itself for a single bench, the bench's index for each of a batch)."""

    def __init__(self, seed: int, device: str, batch: int, benches: Sequence[str] | None = None) -> None:
        if benches is not None and len(benches) != batch:
            raise ValueError(f"{len(benches)} bench names for a batch of {batch}")
        if benches is None and batch == 1:
            self.generators = [device_rng(seed, device)]
        else:
            names = benches if benches is not None else [str(b) for b in range(batch)]
            self.generators = [device_rng(spawned(seed, name), device) for name in names]

    def rows(self, bench: np.ndarray) -> RowNoise:
        """Draws for rows of the benches ``bench`` (one index a row)."""
        return RowNoise(self.generators, bench)

    def per_bench(self) -> RowNoise:
        """Draws of one row per bench, in the batch's order (a bench's clock drift, say)."""
        return RowNoise(self.generators, np.arange(len(self.generators)))


class RowNoise:
    """``numpy.random.Generator``'s ``normal``, ``uniform`` and ``exponential`` for an array whose first axis
    is the rows: the rows of bench b come from b's generator, in their order."""

    def __init__(self, generators: list[np.random.Generator], bench: np.ndarray) -> None:
        bench = np.asarray(bench, dtype=np.int64)
        self.generators, self.n = generators, len(bench)
        if self.n and (bench.min() < 0 or bench.max() >= len(generators)):
            raise ValueError(f"bench indices outside 0…{len(generators) - 1}")
        order = np.argsort(bench, kind="stable")
        present, starts = np.unique(bench[order], return_index=True)
        self.groups = list(zip(present.tolist(), np.split(order, starts[1:]), strict=True)) if self.n else []

    def _draw(self, method: str, size, *args: float) -> np.ndarray:
        size = (size,) if np.isscalar(size) else tuple(size)
        if not size or size[0] != self.n:
            raise ValueError(f"the draws' first axis ({size}) must be the {self.n} rows")
        out = np.empty(size)
        for b, rows in self.groups:
            out[rows] = getattr(self.generators[b], method)(*args, size=(len(rows), *size[1:]))
        return out

    def normal(self, loc: float = 0.0, scale: float = 1.0, size=None) -> np.ndarray:
        return self._draw("normal", size, loc, scale)

    def uniform(self, low: float = 0.0, high: float = 1.0, size=None) -> np.ndarray:
        return self._draw("uniform", size, low, high)

    def exponential(self, scale: float = 1.0, size=None) -> np.ndarray:
        return self._draw("exponential", size, scale)
