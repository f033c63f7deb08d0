"""Bounded in-process memos for pure functions of large inputs (speckle tiles, their spectra).

One process meets the same speckle tile many times: `prepare` builds its model for every layout an
optimizer or a sweep judges, the design checks and σ_measured meet the same pixel footprints. A
`Memo` keeps the last `size` results by a hashable key and drops the oldest first; `digest` makes
such a key from an array's values (blake2b of its bytes, its dtype and shape). Results are handed
out as stored: a memoized array is made read-only so that no caller can change what the next one
gets.
"""

from __future__ import annotations

import hashlib
from typing import Any, Callable, Hashable

import numpy as np


def digest(array) -> str:
    """A 32-hex-digit key of an array's values, dtype and shape (blake2b, 16 bytes)."""
    a = np.ascontiguousarray(array)
    h = hashlib.blake2b(a.tobytes(), digest_size=16)
    h.update(repr((a.dtype.str, a.shape)).encode())
    return h.hexdigest()


class Memo:
    """The last `size` results by key, the oldest dropped first (first in, first out)."""

    def __init__(self, size: int):
        if size < 1:
            raise ValueError(f"size: expected at least 1, got {size!r}")
        self.size = size
        self._items: dict = {}

    def __contains__(self, key: Hashable) -> bool:
        return key in self._items

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, key: Hashable) -> Any:
        return self._items[key]

    def put(self, key: Hashable, value: Any) -> Any:
        """Keep `value` under `key` (the oldest entry leaves when full) and return it."""
        if key not in self._items and len(self._items) >= self.size:
            self._items.pop(next(iter(self._items)))
        self._items[key] = value
        return value

    def get_or(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """The kept result for `key`, else `compute()` kept and returned."""
        if key in self._items:
            return self._items[key]
        return self.put(key, compute())

    def clear(self) -> None:
        self._items.clear()
