"""Timing in turns: every round calls each contender that still wants a call once, in an order shuffled
per round (seeded).

This VM has slow and fast spells of seconds. Contenders timed one after another in blocks caught
different spells (wide-gap's ratio to BIT* read 0.57 and 1.37 in two runs of the same code, 200 calls
each); in turns they share them. The shuffle: in a fixed order each contender always follows the same
one, whose leftovers in the caches favour some (a sub-millisecond call after Informed RRT*'s 8 ms is
slower than after 1 ms).
"""

from __future__ import annotations

import random
from collections.abc import Callable, Mapping, Sequence
from typing import TypeVar

import numpy as np
from scipy import stats

T = TypeVar("T")


def in_turns(
    calls: Mapping[str, Callable[[int], T]],
    wants_more: Callable[[str, list[T]], bool],
    *,
    seed: int,
    on_round: Callable[[int], None] = lambda k: None,
) -> dict[str, list[T]]:
    """Each contender's results, in call order: `calls[name](k)` is its k-th call, made while
    `wants_more(name, its results so far)`; `on_round(k)` before round k."""
    rng = random.Random(seed)
    results: dict[str, list[T]] = {name: [] for name in calls}
    rounds = 0
    while due := [name for name in calls if wants_more(name, results[name])]:
        on_round(rounds)
        rounds += 1
        rng.shuffle(due)
        for name in due:
            results[name].append(calls[name](len(results[name])))
    return results


def ratio_interval(ours_ms: Sequence[float], theirs_ms: Sequence[float], *, level: float = 0.95,
                   resamples: int = 2000, seed: int = 0) -> tuple[float, float] | None:
    """The `level` bootstrap interval (percentile method) of median(ours) ÷ median(theirs), or None with
    fewer than two calls of either: how far the ratio could move with other draws of the same calls.

    The two sets of calls are resampled independently: they were timed in turns, not in pairs. A
    sampling planner's spread (BIT* on corner-trap: 17 to 72 ms between the deciles of 40 runs) makes
    the ratio of two medians of about 30 calls move by 15–20 % from run to run; the interval says so.
    """
    if min(len(ours_ms), len(theirs_ms)) < 2:
        return None
    result = stats.bootstrap(
        (np.asarray(ours_ms), np.asarray(theirs_ms)),
        lambda ours, theirs, axis: np.median(ours, axis=axis) / np.median(theirs, axis=axis),
        vectorized=True, paired=False, n_resamples=resamples, confidence_level=level, method="percentile",
        rng=np.random.default_rng(seed),
    )
    low, high = float(result.confidence_interval.low), float(result.confidence_interval.high)
    return (low, high) if np.isfinite(low) and np.isfinite(high) else None
