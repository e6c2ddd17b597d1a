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
from collections.abc import Callable, Mapping
from typing import TypeVar

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
