"""A few most recently used values kept in a dict: the model fits' per-parameter images (gap/models.py) and the
projector-intrinsics fit's surface points (stages/intrinsics.py), each recomputed otherwise at every column of a
finite-difference Jacobian."""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any


def recent(cache: dict, key: Hashable, make: Callable[[], Any], keep: int = 3) -> Any:
    """``cache[key]``, made by ``make()`` when missing; the ``keep`` most recently used keys stay."""
    value = cache.pop(key, None)
    if value is None:
        value = make()
    cache[key] = value  # reinserted: dicts keep insertion order, so the first key is the least recent
    while len(cache) > keep:
        cache.pop(next(iter(cache)))
    return value
