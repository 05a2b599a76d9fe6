"""Byte-bounded caches an engine owns (renderer/engine.py): ByteLru for device buffers and other per-key values;
Spares for device buffers no render holds any more; the brick pool (renderer/pool.py) shares their bound."""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Callable

__all__ = ["ByteBound", "ByteLru", "Spares"]


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

    def make_room(self, nbytes: int) -> None:
        """Evict the least recently used entries until `nbytes` more fit the bound: what putting an entry of that
        size is going to evict goes before the memory for it is taken (device buffers: renderer/engine.py's
        spares take what is freed)."""
        with self._lock:
            self._evict(self.max_bytes - nbytes, floor=0)

    def clear(self) -> None:
        with self._lock:
            self._d.clear()
            self._bytes = 0

    def _evict(self, bound: int, floor: int | None = None) -> None:
        floor = (1 if self.keep_last else 0) if floor is None else floor
        while self._bytes > bound and len(self._d) > floor:
            _, (_, n) = self._d.popitem(last=False)
            self._bytes -= n


class Spares(ByteBound):
    """Device buffers that nothing uses any more, kept for the next one of about their size (an atlas: a new view
    of a large volume builds one of nearly the same size as the last, and a fresh buffer's pages are zeroed by the
    system as they are first written, a good part of building it). At most `most` buffers, within the bound (a
    function: the room a device cache leaves); `give` keeps the newest. `take(nbytes)` hands over (and forgets)
    the smallest one of at least `nbytes` and at most `slack` times it: the caller owns it then."""

    def __init__(self, max_bytes: "int | Callable[[], int]", most: int = 2, slack: float = 1.0625):
        super().__init__(max_bytes)
        self.most, self.slack = most, slack
        self._held: list[tuple[Any, int]] = []  # (buffer, its bytes), oldest first

    def __len__(self) -> int:
        return len(self._held)

    def give(self, buf: Any, nbytes: int) -> None:
        with self._lock:
            self._held.append((buf, int(nbytes)))
            self._bytes += int(nbytes)
            self._evict()

    def trim(self) -> None:
        """Drop the oldest down to the bound now (it follows the room the device cache leaves)."""
        with self._lock:
            self._evict()

    def _evict(self) -> None:
        bound = self.max_bytes
        while self._held and (len(self._held) > self.most or self._bytes > bound):
            self._bytes -= self._held.pop(0)[1]

    def take(self, nbytes: int) -> Any:
        """A buffer of at least `nbytes` and at most slack × `nbytes` bytes, or None; the others stay."""
        with self._lock:
            fits = [i for i, (_, n) in enumerate(self._held) if nbytes <= n <= self.slack * nbytes]
            if not fits:
                return None
            i = min(fits, key=lambda j: self._held[j][1])
            buf, n = self._held.pop(i)
            self._bytes -= n
            return buf

    def clear(self) -> None:
        with self._lock:
            self._held.clear()
            self._bytes = 0
