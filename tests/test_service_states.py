"""The state machine of jobs and units (service/states.py), by transition."""

from __future__ import annotations

import itertools
from datetime import datetime, timedelta, timezone

import pytest

from service import states
from service.errors import Conflict, IllegalTransition
from service.models import Job, WorkUnit

T0 = datetime(2026, 1, 1, tzinfo=timezone.utc)
T1 = T0 + timedelta(seconds=5)


def make_job(status: str) -> Job:
    return Job(id="abc123abc123", status=status, created=T0)


def make_unit(state: str) -> WorkUnit:
    return WorkUnit(job_id="abc123abc123", index=3, state=state, attempts=1, task_ids=[])


def test01_the_tables_are_exactly_these():
    # A change to the allowed transitions must be deliberate: it changes this test.
    assert {k: set(v) for k, v in states.JOB_TRANSITIONS.items()} == {
        "queued": {"running", "paused", "failed", "canceled"},
        "running": {"done", "paused", "queued", "failed", "canceled"},
        "paused": {"queued", "running", "failed", "canceled"},
        "done": {"queued"}, "failed": {"queued", "running"}, "canceled": {"queued"}}
    assert {k: set(v) for k, v in states.UNIT_TRANSITIONS.items()} == {
        "pending": {"queued", "canceled", "skipped"},  # skipped: a target job's (targets.py)
        # -> pending: withdrawn or preempted for another owner (fairshare.py)
        "queued": {"queued", "running", "done", "failed", "canceled", "pending"},
        "running": {"queued", "done", "failed", "canceled", "pending"},
        "done": set(), "skipped": set(), "failed": {"pending"}, "canceled": {"pending"}}


@pytest.mark.parametrize("old,new", list(itertools.product(states.JOB_STATUSES, repeat=2)))
def test02_every_job_pair_is_allowed_exactly_when_the_table_says(old, new):
    job = make_job(old)
    if new in states.JOB_TRANSITIONS[old]:
        states.change_job(job, new, T1)
        assert job.status == new
    else:
        with pytest.raises(IllegalTransition) as info:
            states.change_job(job, new, T1)
        assert job.status == old, "a refused transition changes nothing"
        assert f"'{old}'" in str(info.value) and f"'{new}'" in str(info.value)


@pytest.mark.parametrize("old,new", list(itertools.product(states.UNIT_STATES, repeat=2)))
def test03_every_unit_pair_is_allowed_exactly_when_the_table_says(old, new):
    unit = make_unit(old)
    if new in states.UNIT_TRANSITIONS[old]:
        states.change_unit(unit, new, T1)
        assert unit.state == new
    else:
        with pytest.raises(IllegalTransition):
            states.change_unit(unit, new, T1)
        assert unit.state == old


def test04_job_queued_to_running_sets_started():
    job = make_job("queued")
    states.change_job(job, "running", T1)
    assert job.started == T1 and job.finished is None


@pytest.mark.parametrize("final", ["done", "failed", "canceled"])
def test05_job_running_to_final_sets_finished(final):
    job = make_job("running")
    states.change_job(job, final, T1, error="why" if final != "done" else None)
    assert job.finished == T1
    assert job.error == ("why" if final != "done" else None)


def test06_job_done_to_canceled_is_a_conflict():
    job = make_job("done")
    with pytest.raises(Conflict, match="allowed from 'done': queued"):
        states.change_job(job, "canceled", T1)
    with pytest.raises(Conflict, match="none, it is final"):
        states.change_unit(make_unit("done"), "pending", T1)


def test07_unit_queued_to_queued_is_a_new_enqueue():
    unit = make_unit("running")
    unit.started_at = T0
    states.change_unit(unit, "queued", T1)
    assert unit.enqueued_at == T1 and unit.started_at is None
    states.change_unit(unit, "queued", T1 + timedelta(seconds=1))
    assert unit.enqueued_at == T1 + timedelta(seconds=1)


def test08_unit_queued_to_running_sets_started_at():
    unit = make_unit("queued")
    states.change_unit(unit, "running", T1)
    assert unit.started_at == T1


def test09_unit_done_to_done_is_illegal():
    # The scheduler relies on this: a unit completes exactly once.
    unit = make_unit("running")
    states.change_unit(unit, "done", T1)
    assert unit.finished_at == T1
    with pytest.raises(IllegalTransition):
        states.change_unit(unit, "done", T1)


def test10_unit_pending_to_running_is_illegal():
    with pytest.raises(IllegalTransition):
        states.change_unit(make_unit("pending"), "running", T1)



def test11_pause_and_resume_keep_started_and_retry_reopens_a_failed_job():
    job = make_job("queued")
    states.change_job(job, "running", T0)
    states.change_job(job, "paused", T1)
    states.change_job(job, "running", T1)
    assert job.started == T0 and job.finished is None
    states.change_job(job, "failed", T1, error="unit 3 failed")
    assert job.finished == T1 and job.error
    states.change_job(job, "running", T1 + timedelta(seconds=1))  # retry
    assert job.started == T0 and job.finished is None and job.error is None


def test12_a_retried_unit_starts_afresh():
    unit = make_unit("queued")
    states.change_unit(unit, "failed", T1, error="boom")
    states.change_unit(unit, "pending", T1)
    assert (unit.attempts, unit.error, unit.enqueued_at, unit.finished_at) == (0, None, None, None)


def test13_elapsed_time_excludes_pauses_and_time_spent_failed():
    at = lambda s: T0 + timedelta(seconds=s)  # noqa: E731
    job = make_job("queued")
    job.spec = {"spp": 4}
    job.width = job.height = 8
    states.change_job(job, "paused", at(0))  # paused before it ever started: not running time
    states.change_job(job, "queued", at(100))
    states.change_job(job, "running", at(110))
    assert job.active_seconds(at(120)) == 10
    states.change_job(job, "paused", at(130))
    assert job.active_seconds(at(500)) == 20  # frozen while paused
    states.change_job(job, "running", at(150))
    assert job.active_seconds(at(160)) == 30
    states.change_job(job, "failed", at(170), error="unit 2 failed")
    assert job.active_seconds(at(999)) == 40  # frozen once final
    states.change_job(job, "running", at(200))  # retried: the 30 s spent failed don't count
    states.change_job(job, "done", at(205))
    assert job.active_seconds(at(999)) == 45 and job.samples_total == 8 * 8 * 4
    assert make_job("queued").active_seconds(at(1)) is None  # not started: no elapsed time


def test14_the_recent_rate_is_measured_between_landings_from_the_restart_tracking_changes():
    at = lambda s: T0 + timedelta(seconds=s)  # noqa: E731
    job = make_job("queued")
    states.change_job(job, "running", at(0))
    job.note_samples(1000, at(40))  # the first landing only starts the measurement:
    assert job.recent_rate is None  # its 40 s held the kernels' warm-up, not rendering
    job.note_samples(1000, at(42))  # a plain average at first: 500/s, not pulled towards 0
    assert job.recent_rate == pytest.approx(500)
    for t in range(43, 100):  # then 2000/s for a minute: the rate follows within a few windows
        job.note_samples(2000, at(t))
    assert job.recent_rate == pytest.approx(2000, rel=1e-3)
    states.change_job(job, "paused", at(100))
    assert job.recent_rate is None
    states.change_job(job, "running", at(140))  # measured again from the resume
    job.note_samples(300, at(141))
    assert job.recent_rate is None
    job.note_samples(300, at(142))
    assert job.recent_rate == pytest.approx(300)
