"""A job's read-ahead (service/frames.Prefetch): one frame ahead, never a queue of stale frames behind the renders."""
from __future__ import annotations

import threading

from lodcast.service.frames import Prefetch
from lodcast.service.settings import Settings

SCENE = {"width": 8, "height": 8, "tf": "ct-bone"}


class Reads:
    """The engine's prefetch, recording which volume each read-ahead was for; the first one waits for `go`."""

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.go = threading.Event()
        self.started = threading.Event()

    def prefetch(self, path, scene) -> int:
        self.calls.append(path.name)
        self.started.set()
        self.go.wait(10)
        return 0


def test_a_read_ahead_replaces_the_ones_still_waiting(tmp_path):
    for v in "abcd":
        (tmp_path / v).mkdir()
    eng = Reads()
    ahead = Prefetch(eng, Settings(root=tmp_path, token=None))
    ahead.next(("a", SCENE))
    assert eng.started.wait(10)
    for v in "bcd":  # frames rendered while the first read-ahead still runs
        ahead.next((v, SCENE))
    eng.go.set()
    assert ahead.wait(10)
    assert eng.calls == ["a", "d"]  # b and c were stale before they could start
    ahead.next(("b", SCENE))  # an idle prefetch starts again
    assert ahead.wait(10)
    assert eng.calls == ["a", "d", "b"]


def test_a_turntable_reads_ahead_only_what_its_atlas_lacks(tmp_path):
    """The first frame renders alone (a read ahead beside it would read the same bricks at the same time); later
    frames read the next one ahead, which finds every brick in the newest atlas on the device and reads nothing."""
    from lodcast.service.frames import FrameRenderer
    from lodcast.service.jobs import parse_job, plan_frames
    from lodcast.service.queue import JobQueue
    from lodcast.service.rendering import RenderEngine
    from lodcast.service.testing import make_volume

    make_volume(tmp_path, "v", n=48, block_size=8)
    settings = Settings(root=tmp_path, token=None)
    reads: list[int] = []

    class Counting(RenderEngine):
        def prefetch(self, path, scene):
            n = super().prefetch(path, scene)
            reads.append(n)
            return n

    eng = Counting(settings)
    jq = JobQueue(settings, engine=eng)
    job = parse_job({"kind": "turntable", "volume": "v", "frames": 4,
                     "scene": {"width": 32, "height": 32, "tf": "ct-bone", "quality": {"reduction": 8}}})
    jid = jq.submit(job)["id"]
    plan = plan_frames(job)
    names = [f"frame_{i:05d}.png" for i in range(len(plan))]
    frames = FrameRenderer(settings, jq.records, jid, plan, jq.files(jid), names, eng)
    first = eng.renderer.render(eng.store(tmp_path / "v"), plan[0][1])
    assert first.report["bricks_read"] > 0  # the selection reads the store (a fresh engine in the job below)
    eng.renderer.close()
    eng = Counting(settings)
    frames = FrameRenderer(settings, jq.records, jid, plan, jq.files(jid), names, eng)
    for i in range(len(plan)):
        assert frames.render(i, "me", i + 1 if i + 1 < len(plan) else None)
    assert frames.ahead.wait(30)
    assert reads == [0, 0]  # frames 2 and 3, read ahead beside frames 1 and 2: all on the device already
    assert sorted(jq.files(jid).names()) == names
