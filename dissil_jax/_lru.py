"""A bounded least-recently-used mapping, for the host-side caches keyed by supply rate."""

from __future__ import annotations

import collections
from collections.abc import Callable, Hashable
from typing import Any


class LRU:
    """At most `size` entries; a lookup or store marks an entry as the most recently used,
    and a store beyond `size` drops the least recently used. Not locked: callers that share
    one across threads hold their own lock."""

    def __init__(self, size: int):
        self.size = int(size)
        self._data: collections.OrderedDict = collections.OrderedDict()

    def __len__(self) -> int:
        return len(self._data)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._data

    def clear(self) -> None:
        self._data.clear()

    def keys(self) -> list:
        """The keys, least recently used first."""
        return list(self._data)

    def get(self, key: Hashable, default: Any = None) -> Any:
        if key not in self._data:
            return default
        self._data.move_to_end(key)
        return self._data[key]

    def put(self, key: Hashable, value: Any) -> None:
        self._data[key] = value
        self._data.move_to_end(key)
        while len(self._data) > self.size:
            self._data.popitem(last=False)

    def get_or_build(self, key: Hashable, build: Callable[[], Any]) -> Any:
        """`get(key)`, or `build()` stored under `key` when missing."""
        if key in self._data:
            return self.get(key)
        value = build()
        self.put(key, value)
        return value
