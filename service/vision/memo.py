"""Per-object memo for work the estimate hot path must not redo each frame (template tables made from
a bank, a camera, an image size): a small LRU keyed by the owner's id, checked by identity so a
recycled id never returns another object's tables. Thread-safe (the API estimates in a threadpool);
two threads missing the same key at once both make it, and one result is kept."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import TypeVar

T = TypeVar("T")


class Memo:
    def __init__(self, size: int) -> None:
        self.size = size
        self._items: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def peek(self, owner: object, key: Hashable) -> object | None:
        """The value kept for (``owner``, ``key``), or None (nothing is made)."""
        with self._lock:
            hit = self._items.get((id(owner), key))
            return hit[1] if hit is not None and hit[0] is owner else None

    def get(self, owner: object, key: Hashable, make: Callable[[], T]) -> T:
        """``make()`` for (``owner``, ``key``), made once while it stays among the ``size`` latest."""
        k = (id(owner), key)
        with self._lock:
            hit = self._items.get(k)
            if hit is not None and hit[0] is owner:
                self._items.move_to_end(k)
                return hit[1]
        value = make()  # outside the lock: a slow make must not stall other banks' estimates
        with self._lock:
            self._items[k] = (owner, value)
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return value

    def clear(self) -> None:
        """Forget every value (the next ``get`` of any key makes it again, as in a fresh process)."""
        with self._lock:
            self._items.clear()
