"""Byte-bounded caches an engine owns (renderer/engine.py): ByteLru for device buffers and other per-key values;
the brick pool (renderer/pool.py) shares its bound."""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Callable

__all__ = ["ByteBound", "ByteLru"]


class ByteBound:
    """What a byte-bounded store shares: its bound (`max_bytes`: a number, or a function of no arguments asked each
    time, for a bound that follows the environment), the bytes it holds and the lock that guards them."""

    def __init__(self, max_bytes: "int | Callable[[], int]"):
        self._max = max_bytes
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def max_bytes(self) -> int:
        return int(self._max() if callable(self._max) else self._max)

    @property
    def nbytes(self) -> int:
        return self._bytes


class ByteLru(ByteBound):
    """Thread-safe LRU bounded by the bytes of its values (`max_bytes`: a number, or a function of no arguments
    asked at every insertion, for a bound that follows the environment). `keep_last`: the newest entry stays even
    when it alone exceeds the bound (else an entry larger than the bound is not kept at all)."""

    def __init__(self, max_bytes: "int | Callable[[], int]", keep_last: bool = False):
        super().__init__(max_bytes)
        self.keep_last = keep_last
        self._d: OrderedDict[Any, tuple[Any, int]] = OrderedDict()

    def __len__(self) -> int:
        return len(self._d)

    def get(self, key: Any) -> Any:
        with self._lock:
            hit = self._d.get(key)
            if hit is None:
                return None
            self._d.move_to_end(key)
            return hit[0]

    def put(self, key: Any, value: Any, nbytes: int) -> None:
        with self._lock:
            old = self._d.pop(key, None)
            if old is not None:
                self._bytes -= old[1]
            bound = self.max_bytes  # once: a function bound is asked per insertion (a million bricks in a cold image)
            if nbytes > bound and not self.keep_last:
                return
            self._d[key] = (value, int(nbytes))
            self._bytes += int(nbytes)
            self._evict(bound)

    def trim(self) -> None:
        """Evict down to the bound now (a bound that is a function may have shrunk since the last insertion)."""
        with self._lock:
            self._evict(self.max_bytes)

    def clear(self) -> None:
        with self._lock:
            self._d.clear()
            self._bytes = 0

    def _evict(self, bound: int) -> None:
        floor = 1 if self.keep_last else 0
        while self._bytes > bound and len(self._d) > floor:
            _, (_, n) = self._d.popitem(last=False)
            self._bytes -= n
