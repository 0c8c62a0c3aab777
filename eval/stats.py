"""Seed-level statistics for results tables: each row's mean ± sd over training seeds with the
95% t-interval of the mean, and paired contrasts between rows.

The unit of replication is the training seed, not the episode: two policies trained with
different seeds differ by more than their episodes' binomial noise, so intervals over pooled
episodes overstate what a table resolves. Seed s of every row shares its episode order and
initialisation, so rows are compared seed by seed (the paired difference), which removes the
part of the spread the rows share.
"""

from __future__ import annotations

import math
from typing import Mapping, NamedTuple, Sequence

import numpy as np
from scipy import stats


class SeedSummary(NamedTuple):
    """A quantity over n seeds: mean, sample sd, and the 95% t-interval of the mean
    (lo = hi = mean, sd = 0 for one seed: no interval)."""

    n: int
    mean: float
    sd: float
    lo: float
    hi: float

    def text(self, digits: int = 1, signed: bool = False) -> str:
        """'mean ± sd [lo, hi] (n)', or 'mean (1 seed)'."""
        f = f"{{:+.{digits}f}}" if signed else f"{{:.{digits}f}}"
        if self.n == 1:
            return f"{f.format(self.mean)} (1 seed)"
        return (f"{f.format(self.mean)} ± {self.sd:.{digits}f} [{f.format(self.lo)}, {f.format(self.hi)}] "
                f"(n={self.n})")


def seed_summary(values: Sequence[float], confidence: float = 0.95) -> SeedSummary:
    """Mean, sd (ddof 1) and the `confidence` t-interval over seeds. ValueError for no values
    or a non-finite one."""
    x = np.asarray(values, dtype=np.float64)
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"need a 1-D list of per-seed values, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"per-seed values must be finite, got {x.tolist()}")
    n, mean = x.size, float(x.mean())
    if n == 1:
        return SeedSummary(1, mean, 0.0, mean, mean)
    sd = float(x.std(ddof=1))
    half = float(stats.t.ppf(0.5 + confidence / 2, n - 1)) * sd / math.sqrt(n)
    return SeedSummary(n, mean, sd, mean - half, mean + half)


def paired_difference(row: Mapping[int, float], reference: Mapping[int, float],
                      confidence: float = 0.95) -> SeedSummary:
    """The paired contrast row − reference over the seeds both have (by seed number): the mean
    difference with its t-interval. ValueError when they share no seed."""
    seeds = sorted(set(row) & set(reference))
    if not seeds:
        raise ValueError(f"no seed in common: row has {sorted(row)}, reference has {sorted(reference)}")
    return seed_summary([row[s] - reference[s] for s in seeds], confidence)


def resolved(contrast: SeedSummary) -> bool:
    """Whether a contrast's interval excludes zero (a single seed resolves nothing)."""
    return contrast.n > 1 and (contrast.lo > 0 or contrast.hi < 0)
