"""Rendering a job's frames: one frame under its lease, and the next frame's bricks read ahead.

The worker that owns a job and the idle workers that help it (service/queue.py) render frames through the same
FrameRenderer: a frame is rendered only by the worker holding its lease (records.lease), renewed every heartbeat
while it renders, and written to the job's results (service/results.py).
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any

from lodcast.service.rendering import encode, parse_scene
from lodcast.service.results import JobFiles
from lodcast.service.volumes import volume_path

__all__ = ["FrameRenderer", "Prefetch"]

log = logging.getLogger("lodcast.service.queue")


class FrameRenderer:
    """Rendering one frame of a job under its lease (records.lease), for the job's owner and its helpers alike: a
    frame is rendered only by the worker that holds its lease, renewed every heartbeat while it renders, so that
    each frame is rendered once while its worker lives (and again only after that worker died mid-frame)."""

    def __init__(self, settings: Any, records: Any, job_id: str, plan: list, files: JobFiles, names: list[str],
                 eng: Any) -> None:
        self.settings, self.records = settings, records
        self.job_id, self.plan, self.files, self.names = job_id, plan, files, names
        self.eng = eng
        self.ahead = Prefetch(self.eng, settings)
        # the first frame renders alone: a read ahead beside it would read most of the same bricks at the same
        # time (the next frame's are told from the newest atlas, which the first frame has not made yet)
        self.rendered = False

    def render(self, i: int, owner: str, nxt: int | None) -> bool:
        """Render frame i if its lease can be had; whether it was rendered here."""
        st, rec = self.settings, self.records
        if not rec.lease(self.job_id, i, owner, st.stale_after_s):
            return False
        stop = threading.Event()

        def renew() -> None:
            while not stop.wait(st.heartbeat_s):
                try:
                    rec.lease(self.job_id, i, owner, st.stale_after_s)
                except Exception:  # noqa: BLE001 - a missed renewal only risks a second render of this frame
                    log.exception("job %s: renewing the lease of frame %d", self.job_id, i)

        keeper = threading.Thread(target=renew, daemon=True, name=f"lease-{self.job_id[:8]}-{i}")
        keeper.start()
        try:
            if self.files.exists(self.names[i]):  # written between the look and the lease
                return False
            vid, scene_dict = self.plan[i]
            scene = parse_scene(scene_dict, st, ("scene",))
            if nxt is not None and self.rendered:
                self.ahead.next(self.plan[nxt])
            result = self.eng.render(volume_path(st.root, vid), scene, st.max_samples)
            self.rendered = True
            data, _ = encode(result, scene)
            self.files.write(self.names[i], data)
        finally:
            stop.set()
            keeper.join(timeout=5)
        log.info("job %s: frame %d rendered by %s", self.job_id, i, owner)
        if st.frame_delay_s:
            time.sleep(st.frame_delay_s)
        rec.update(self.job_id, {"done": len(self.files.names() & set(self.names))}, expect={"state": ("running",)})
        return True


class Prefetch:
    """Reads the next frame's bricks into the brick cache while the current frame renders (a TF sweep or a scenes
    job changes the selection from frame to frame). One frame ahead, on one thread: a request made while a read
    ahead runs replaces any that is still waiting, so frames that outpace the reads never queue work behind them.
    A failure only costs the prefetch (the render reads the bricks itself and reports any error)."""

    def __init__(self, eng: Any, settings: Any):
        self.eng, self.settings = eng, settings
        self._lock = threading.Lock()
        self._idle = threading.Condition(self._lock)
        self._waiting: tuple[str, Any] | None = None
        self._running = False

    def next(self, item: tuple[str, Any] | None) -> None:
        if item is None:
            return
        with self._lock:
            self._waiting = item
            if self._running:
                return
            self._running = True
        threading.Thread(target=self._drain, daemon=True, name="lodcast-prefetch").start()

    def _drain(self) -> None:
        while True:
            with self._lock:
                item, self._waiting = self._waiting, None
                if item is None:
                    self._running = False
                    self._idle.notify_all()
                    return
            self._run(*item)

    def wait(self, timeout: float | None = None) -> bool:
        """Until no read ahead runs or waits (False: `timeout` seconds passed first)."""
        with self._idle:
            return self._idle.wait_for(lambda: not self._running, timeout)

    def _run(self, vid: str, scene_dict: Any) -> None:
        try:
            scene = parse_scene(scene_dict, self.settings, ("scene",))
            self.eng.prefetch(volume_path(self.settings.root, vid), scene)
        except Exception as exc:  # the render of that frame meets (and reports) whatever this met
            log.debug("prefetch of a frame of %s failed: %s", vid, exc)
