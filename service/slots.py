"""The service's render slots: at most `size` renders at once, shared out among the volumes being viewed.

Plain arrival order (a FIFO semaphore) lets two renders of one volume hold both slots while the other volumes'
viewers wait: two viewers opening a large volume whose bricks are not cached yet each read the same bricks, for
seconds, and every other viewer waits for both. Here a volume holds at most its share of the slots, `size`
divided among the volumes in use (rounded up): those with renders running or waiting, or one finished less than
`linger_s` ago (a viewer sends its next request as soon as it has the last image: between two of them its volume
is still in use). A freed slot goes to the earliest waiting render whose volume is below its share. So the second
viewer of a cold volume starts when the first is done and finds the bricks cached, while the other volumes keep
their slot; one volume alone, or one slot, is plain arrival order.

No render waits for ever: it is passed over only while its own volume holds its share, and only by renders that
arrived before it or whose volumes are below theirs; when its volume's running renders end, it is the earliest
of that volume and below any share.

One asyncio loop uses a Slots (the app makes one per running loop).
"""
from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections import Counter
from typing import AsyncIterator, Callable, Hashable

__all__ = ["Slots"]


class Slots:
    """`size` render slots shared out among volumes (module docstring); `async with slots.slot(volume): ...`.
    `clock`: seconds, for `linger_s` (tests give their own)."""

    def __init__(self, size: int, linger_s: float = 2.0, clock: Callable[[], float] = time.monotonic) -> None:
        if size < 1:
            raise ValueError(f"size must be at least 1, got {size}")
        self._size = size
        self._linger = linger_s
        self._clock = clock
        self._busy = 0
        self._running: Counter[Hashable] = Counter()  # volume -> its renders holding a slot
        self._waiting: list[tuple[Hashable, asyncio.Future[None]]] = []  # in arrival order
        self._ended: dict[Hashable, float] = {}  # volume -> when its last render ended

    @property
    def waiting(self) -> int:
        return len(self._waiting)

    @contextlib.asynccontextmanager
    async def slot(self, volume: Hashable) -> AsyncIterator[None]:
        await self._acquire(volume)
        try:
            yield
        finally:
            self._release(volume)

    def _share(self, volume: Hashable) -> int:
        now = self._clock()
        self._ended = {v: t for v, t in self._ended.items() if now - t < self._linger}
        in_use = {volume, *self._running, *self._ended, *(v for v, _ in self._waiting)}
        return math.ceil(self._size / len(in_use))

    def _may_start(self, volume: Hashable) -> bool:
        return self._busy < self._size and self._running[volume] < self._share(volume)

    async def _acquire(self, volume: Hashable) -> None:
        entry = (volume, asyncio.get_running_loop().create_future())
        self._waiting.append(entry)
        self._grant()  # this one, if a slot is free and nobody before it may take it
        if entry[1].done():
            return
        try:
            await entry[1]
        except BaseException:  # the request went away (its client hung up) while waiting
            if entry in self._waiting:
                self._waiting.remove(entry)
                self._grant()  # it may have held back others of its volume
            elif entry[1].done() and not entry[1].cancelled():
                self._release(volume)  # granted as it went: the slot goes to the next
            raise

    def _take(self, volume: Hashable) -> None:
        self._busy += 1
        self._running[volume] += 1

    def _release(self, volume: Hashable) -> None:
        self._busy -= 1
        self._running[volume] -= 1
        if self._running[volume] <= 0:
            del self._running[volume]
        self._ended[volume] = self._clock()
        self._grant()

    def _grant(self) -> None:
        while self._busy < self._size:
            pick = next((i for i, (v, f) in enumerate(self._waiting) if not f.done() and self._may_start(v)), None)
            if pick is None:
                return
            volume, fut = self._waiting.pop(pick)
            self._take(volume)
            fut.set_result(None)
