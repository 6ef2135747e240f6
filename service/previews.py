"""The running previews of jobs in flight: each landed unit's film is added
to an in-memory `renderer.Film` per job (`Film.add`: the one definition of
"merging is addition"), and the job's `preview.png` and `noise.png` are
written from it at most every `PREVIEW_INTERVAL` seconds (the first unit's
at once), and no sooner than `PREVIEW_PACE` times the CPU its last write
took, each write announced as a `preview` event.

Only what someone looks at is written. After the first unit's images, a
job's preview (or noise map) is rewritten only while a client has fetched
it within `WATCH_SECONDS` (`Store.mark_watched`, called by the GET routes:
the dashboard fetches the image again on every `preview` event, so an open
job page keeps it coming). Most jobs of a farm run unwatched, and their
previews (tonemap, noise map, two PNG encodes: 32 ms per write at
256 x 256) were 40 % of the service's CPU for a 10-s one-pass job on the
2-core machine (0.49 s, 0.29 s without them). A frame nobody looks at stays
dirty; the first GET after a while returns the last image written, and the
next tick (at most a second later) writes the current one. The frame's float
channels go with the preview (`Store.frame_path`, for the HDR viewer:
service.pixels); the final images
come from the merge (`service.results`) whatever happened here.

    previews = RunningPreviews(store, hub, done_units=lambda job_id: [...])
    units = previews.refresh(job_id, width, height, landed)   # written: units in it
    if units is not None: previews.publish(job_id, units)

Frames are float32, every layer of them (28 bytes a pixel, 56 with AOVs,
more with splats or jackknife sums), and kept up to `PREVIEW_BYTES` in all
(jobs interleave, so every running job's frame is in use); beyond that the
one cheapest to rebuild goes. A write makes its images band by band
(`renderer.Film.images`): its float64 temporaries are a band's. A frame
missing after a restart or an eviction is rebuilt from the stored films of
the done units, at most once per `PREVIEW_INTERVAL` per job (a rebuild
reads every done unit). The order of addition does not matter
for a preview; the final EXR is merged from the stored films in unit order
(`service.results`).
"""

from __future__ import annotations

import itertools
import time
from typing import Callable, Iterable

import numpy as np

from renderer import Film, PartialFilm

from .events import EventHub
from .pixels import write_frame
from .store import Store

__all__ = ["RunningPreviews", "PREVIEW_INTERVAL", "PREVIEW_PACE", "PREVIEW_BYTES", "WATCH_SECONDS",
           "preview_event"]

PREVIEW_INTERVAL = 1.0  # seconds between two writes of a job's running preview, at least
# A write costs CPU in proportion to the frame: tonemapping, the noise map and
# two PNGs took 32 ms for 256 x 256 pixels on the 2-core machine (about 1 s
# for a 1920 x 1080 frame). On a machine whose cores the render processes
# use, a preview every second of such a frame would take a core from them;
# at PREVIEW_PACE times its own cost apart, a job's previews use at most
# about 2 % of one.
PREVIEW_PACE = 50.0
PREVIEW_BYTES = 256 << 20  # running previews kept in memory (float32: 28 bytes a pixel and up)
# A client that fetched a job's preview (or noise map) this recently is
# looking at it: its next writes are made. The dashboard fetches it again
# after every write, so this only has to outlast the gap between two writes.
WATCH_SECONDS = 30.0


class _Frame:
    """A job's running preview: a float32 Film, the units in it, when it was written."""

    def __init__(self, width: int, height: int):
        self.film = Film(0, 0, np.zeros((height, width, 3), np.float32),
                         np.zeros((height, width, 3), np.float32),
                         np.zeros((height, width), np.float32))
        self.added: set[int] = set()
        self.written = -1e9  # time.monotonic() of the last PNG
        self.interval = PREVIEW_INTERVAL  # before the next (see PREVIEW_PACE)
        self.dirty = False
        self.ever_written = False  # the first write is made whether anyone looks or not
        self.watched = (False, False)  # (preview, noise) fetched within WATCH_SECONDS
        self.watch_read = -1e9  # time.monotonic() the markers were last read

    @property
    def nbytes(self) -> int:
        f = self.film
        return sum(a.nbytes for a in (f.sum, f.sum_sq, f.weight, f.splat, f.splat_sq, f.aov,
                                      f.jackknife) if a is not None)

    def add(self, index: int, part: PartialFilm) -> None:
        if index not in self.added:
            self.film.add(part)
            self.added.add(index)
            self.dirty = True


class RunningPreviews:
    """The previews of the jobs in flight (module doc); one thread (the scheduler's)."""

    def __init__(self, store: Store, hub: EventHub,
                 done_units: Callable[[str], Iterable[int]]):
        self.store, self.events, self._done_units = store, hub, done_units
        self._versions = itertools.count(1)
        self._frames: dict[str, _Frame] = {}  # least recently used first
        self._rebuilt: dict[str, float] = {}  # job -> time.monotonic() of its last rebuild

    def dirty(self, job_id: str) -> bool:
        """Has the job's frame units not yet written that someone looks at
        (a throttled preview)?"""
        frame = self._frames.get(job_id)
        return frame is not None and frame.dirty and any(self._wanted(job_id, frame))

    def _wanted(self, job_id: str, frame: _Frame) -> tuple[bool, bool]:
        """(preview, noise): which images a write makes. Both the first time;
        then those fetched within WATCH_SECONDS (the markers are read at most
        once per PREVIEW_INTERVAL: a stat each)."""
        if not frame.ever_written:
            return True, True
        now = time.monotonic()
        if now - frame.watch_read >= PREVIEW_INTERVAL:
            frame.watch_read = now
            since = time.time() - WATCH_SECONDS
            frame.watched = (self.store.watched_at(job_id, "preview") >= since,
                             self.store.watched_at(job_id, "noise") >= since)
        return frame.watched

    def ever_written(self, job_id: str) -> bool:
        """Has this job's running preview been written (since this scheduler
        started, or the frame was last dropped)?"""
        frame = self._frames.get(job_id)
        return frame is not None and frame.ever_written

    def keep_only(self, job_ids) -> None:
        """Forget the frames of jobs no longer scheduled."""
        for job_id in [j for j in self._frames if j not in job_ids]:
            del self._frames[job_id]
        for job_id in [j for j in self._rebuilt if j not in job_ids]:
            del self._rebuilt[job_id]

    def drop(self, job_id: str) -> None:
        self._frames.pop(job_id, None)

    def refresh(self, job_id: str, width: int, height: int,
                landed: list[tuple[int, PartialFilm]]) -> int | None:
        """Add the units that just landed (committed as done) to the job's frame
        and write its PNGs if it changed and the last write is old enough;
        returns the number of units in what was written, or None."""
        frame = self._frames.pop(job_id, None)
        if frame is None:
            if not landed:
                return None
            now = time.monotonic()
            if now - self._rebuilt.get(job_id, -1e9) < PREVIEW_INTERVAL:
                return None  # rebuilt a moment ago: what landed since joins the next rebuild
            self._rebuilt[job_id] = now
            frame = _Frame(width, height)
            fresh = {index for index, _ in landed}
            for index in self._done_units(job_id):  # after a restart or an eviction
                if index not in fresh:
                    frame.add(index, PartialFilm.from_bytes(self.store.unit_film(job_id, index)))
        for index, film in landed:
            frame.add(index, film)
        self._frames[job_id] = frame  # most recently used last
        self._evict(keep=job_id)
        if not frame.dirty or time.monotonic() - frame.written < frame.interval:
            return None
        preview, noise = self._wanted(job_id, frame)
        if not (preview or noise):
            return None  # nobody looks: stays dirty until someone does (module doc)
        cpu = time.thread_time()
        self.store.preview_path(job_id).parent.mkdir(parents=True, exist_ok=True)
        if preview:
            frame.film.write_png(self.store.preview_path(job_id))
            write_frame(self.store, job_id, frame.film)  # the HDR viewer's floats (service.pixels)
        if noise:
            frame.film.write_noise_png(self.store.noise_path(job_id))
        frame.interval = max(PREVIEW_INTERVAL, PREVIEW_PACE * (time.thread_time() - cpu))
        frame.written, frame.dirty, frame.ever_written = time.monotonic(), False, True
        return len(frame.added)

    def _evict(self, keep: str) -> None:
        """Drop frames beyond `PREVIEW_BYTES`, those with the fewest units added
        first (the cheapest to rebuild), never `keep`'s."""
        total = sum(f.nbytes for f in self._frames.values())
        for job_id in sorted(self._frames, key=lambda j: len(self._frames[j].added)):
            if total <= PREVIEW_BYTES:
                break
            if job_id != keep:
                total -= self._frames.pop(job_id).nbytes

    def publish(self, job_id: str, units: int) -> None:
        """Announce that the job's preview and noise map were rewritten."""
        self.events.publish("preview", job_id,
                            preview_event(job_id, next(self._versions), units))


def preview_event(job_id: str, version: int | str, units: int) -> dict:
    """The data of a `preview` event (service.events): where the rewritten
    preview and noise map are, `version` busting the browser's cache."""
    return {"job_id": job_id, "version": version, "units": units,
            "url": f"/jobs/{job_id}/preview.png?v={version}",
            "noise_url": f"/jobs/{job_id}/noise.png?v={version}"}
