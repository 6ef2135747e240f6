"""service.previews: a job's running preview is the plain sum (Film.add) of
the films that landed, written at most once per PREVIEW_INTERVAL, rebuilt
from the stored films after an eviction or restart; after the first, only
the images a client fetched lately are written."""

from __future__ import annotations

import os

import numpy as np

from renderer import PartialFilm, merge
from service.events import EventHub
from service.previews import RunningPreviews
from service.store import Store

JOB = "0123456789ab"


def tile(x0: int, value: float, samples: int = 4) -> PartialFilm:
    film = PartialFilm.zeros(x0, 0, 4, 4)
    film.sum[:] = value * samples
    film.sum_sq[:] = value * value * samples
    film.weight[:] = samples
    return film


def watched(store: Store, *images: str) -> Store:
    for image in images:
        store.mark_watched(JOB, image)
    return store


def test01_the_frame_is_the_sum_of_what_landed_and_writes_are_throttled(tmp_path):
    store = Store(tmp_path)
    done: list[int] = []
    previews = RunningPreviews(store, EventHub(), lambda job_id: done)
    first = [(0, tile(0, 0.25)), (1, tile(4, 0.5))]
    assert previews.refresh(JOB, 8, 4, first) == 2  # the first landing is written at once
    assert store.preview_path(JOB).is_file() and store.noise_path(JOB).is_file()
    watched(store, "preview", "noise")
    frame = previews._frames[JOB].film
    expected = merge(8, 4, [f for _, f in first])
    np.testing.assert_allclose(frame.mean(), expected.mean(), rtol=1e-6)
    # Within PREVIEW_INTERVAL: added, not written; the scheduler visits it again.
    assert previews.refresh(JOB, 8, 4, [(2, tile(0, 1.0))]) is None
    assert previews.dirty(JOB)
    # The same unit twice (a duplicate landing) is added once.
    previews.refresh(JOB, 8, 4, [(2, tile(0, 1.0))])
    assert previews._frames[JOB].film.weight[0, 0] == 8


def test02_an_evicted_frame_is_rebuilt_from_the_stored_films(tmp_path):
    store = Store(tmp_path)
    films = {0: tile(0, 0.25), 1: tile(4, 0.5)}
    for index, film in films.items():
        store.put_unit_film(JOB, index, film.to_bytes())
    previews = RunningPreviews(store, EventHub(), lambda job_id: [0, 1, 2])
    landed = tile(0, 1.0)
    assert previews.refresh(JOB, 8, 4, [(2, landed)]) == 3
    expected = merge(8, 4, [*films.values(), landed])
    np.testing.assert_allclose(previews._frames[JOB].film.mean(), expected.mean(), rtol=1e-6)
    previews.keep_only(set())
    assert not previews.dirty(JOB) and JOB not in previews._frames


def test03_a_costly_preview_is_written_less_often(tmp_path, monkeypatch):
    """The next write waits PREVIEW_PACE times the CPU the last one took, if
    that is longer than PREVIEW_INTERVAL: a big frame's previews must not take
    a core from the render processes."""
    from service import previews as module

    store = Store(tmp_path)
    previews = RunningPreviews(store, EventHub(), lambda job_id: [])
    assert previews.refresh(JOB, 8, 4, [(0, tile(0, 0.25))]) == 1
    watched(store, "preview")
    frame = previews._frames[JOB]
    assert frame.interval == module.PREVIEW_INTERVAL  # a tiny frame: the floor
    monkeypatch.setattr(module, "PREVIEW_PACE", 1e7)  # as if a write took 1e-7 of the pace
    frame.written -= 2 * module.PREVIEW_INTERVAL
    assert previews.refresh(JOB, 8, 4, [(1, tile(4, 0.5))]) == 2  # written; now it was costly
    assert frame.interval > 10 * module.PREVIEW_INTERVAL
    frame.written -= 2 * module.PREVIEW_INTERVAL  # past the floor, not past the pace
    assert previews.refresh(JOB, 8, 4, [(2, tile(0, 1.0))]) is None and previews.dirty(JOB)
    frame.written -= frame.interval
    assert previews.refresh(JOB, 8, 4, []) == 3


def test04_after_the_first_only_what_someone_looks_at_is_written(tmp_path, monkeypatch):
    """An unwatched job's frame takes what lands but writes nothing after its
    first images (and asks for no visit); a GET of one image (Store.mark_watched)
    brings that image's writes back, and an old GET counts for nothing."""
    from service import previews as module

    store = Store(tmp_path)
    previews = RunningPreviews(store, EventHub(), lambda job_id: [])
    assert previews.refresh(JOB, 8, 4, [(0, tile(0, 0.25))]) == 1  # the first: both images
    frame = previews._frames[JOB]

    def stamp(path):  # the bytes: a write of the grown frame changes them
        return path.read_bytes()

    def later():  # past the throttle and the markers' read interval
        frame.written -= 2 * frame.interval
        frame.watch_read -= 2 * module.PREVIEW_INTERVAL

    first = (stamp(store.preview_path(JOB)), stamp(store.noise_path(JOB)))
    later()
    assert previews.refresh(JOB, 8, 4, [(1, tile(4, 0.5))]) is None  # nobody looks
    assert frame.dirty and not previews.dirty(JOB)  # no visits for it either
    assert (stamp(store.preview_path(JOB)), stamp(store.noise_path(JOB))) == first
    assert frame.film.weight[0, 4] == 4  # the unit is in the frame all the same

    store.mark_watched(JOB, "preview")
    later()
    assert previews.dirty(JOB)  # written at the next tick, with no unit landing
    assert previews.refresh(JOB, 8, 4, []) == 2
    assert stamp(store.preview_path(JOB)) != first[0] and stamp(store.noise_path(JOB)) == first[1]

    old = store.watch_path(JOB, "preview")  # fetched longer ago than WATCH_SECONDS
    past = old.stat().st_mtime - module.WATCH_SECONDS - 1
    os.utime(old, (past, past))
    later()
    assert previews.refresh(JOB, 8, 4, [(2, tile(0, 1.0))]) is None and not previews.dirty(JOB)


def test05_marking_a_job_watched_never_makes_its_directory(tmp_path):
    """A GET before the first unit, or racing a delete, leaves no directory behind."""
    store = Store(tmp_path)
    store.mark_watched(JOB, "noise")
    assert not store.job_dir(JOB).exists() and store.watched_at(JOB, "noise") == float("-inf")


def test06_a_job_that_lands_whole_in_one_tick_has_its_preview_before_its_merge(tmp_path,
                                                                                monkeypatch):
    """The API shows preview_url from the first landed unit on. A job whose
    units all land in one tick is complete at once, and its final merge
    (which may take long: a big frame, a denoise) writes the final images
    only later: the first preview must be there when the landing commits."""
    from fake_executor import FakeExecutor
    from service import jobs, scheduler as scheduler_module
    from service.access import Principal
    from service.db import open_ledger
    from service.models import utcnow
    from service.scheduler import Scheduler
    from service.schemas import JobCreate
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", broker_url="", database_url="")
    engine, sessions = open_ledger(settings)
    store = Store(settings.data_dir)
    executor = FakeExecutor(slots=8)
    scheduler = Scheduler(settings, sessions, store, executor)
    with sessions.begin() as session:
        job_id = jobs.create_job(session, store, settings, Principal("admin", "admin"), JobCreate(
            scene="cornell-box", method="path", spp=4, depth=1, width=16, height=16,
            tile_size=8, progressive=False), utcnow()).id
    scheduler.tick()  # planned, its 4 units in flight
    for ticket in executor.submitted:
        executor.finish(job_id, ticket.index)
    seen = []
    write_result = scheduler_module.write_result
    monkeypatch.setattr(scheduler_module, "write_result", lambda store_, job, *a, **k: (
        seen.append(store_.preview_path(job).is_file()), write_result(store_, job, *a, **k))[1])
    scheduler.tick()  # all four land: complete, merged
    assert seen == [True]
    engine.dispose()
