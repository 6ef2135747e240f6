"""A running unit can be stopped, and no owner holds the render processes.

test01 stops a rendering unit of the local pool; test02/test03 cancel a
running job on the embedded service and on a Celery worker, and the freed
process takes the next job's unit; test04 stops a unit over its time budget
(an attempt spent each time, then the job fails); test05-07 drive fair share
over the render processes on a fake executor (who is withdrawn, who is
preempted, and when nobody is); test08/test09 let a newcomer's unit run
while another owner's long units hold every process, on the embedded pool
and on Celery, with both images bit-identical to undisturbed renders.

The long units would take minutes if nothing stopped them (about 3.5 us a
sample on the 2-core machine, where 64 x 64 pixels at 32,768 spp took 465 s),
so on code that cannot stop a unit each test times out; the waits are
generous, and no test asserts how fast anything was (bench/preemption.py
measures that).
"""

from __future__ import annotations

import pytest

from conftest import wait_for

# One unit of 64 x 64 pixels at 16,384 spp: minutes on one core.
LONG = {"scene": "cornell-box", "method": "path", "spp": 16384, "depth": 3, "width": 64,
        "height": 64, "tile_size": 64, "progressive": False}


# -- the local pool ----------------------------------------------------------------------

def test01_the_local_pool_stops_a_rendering_unit_and_the_slot_takes_the_next():
    from renderer import (METHODS, LocalPool, PartialFilm, RenderSpec, UnitStopped,
                          resolve_document, scene_text)

    key, text = scene_text(resolve_document("cornell-box"))
    long_spec = RenderSpec(spp=16384, depth=3, width=64, height=64, tile_size=64)
    long_unit = METHODS["path"].make_plan(long_spec, False)[0].to_dict()
    small = RenderSpec(spp=4, depth=1, width=8, height=8, tile_size=8)
    small_unit = METHODS["path"].make_plan(small, False)[0].to_dict()
    with LocalPool(1) as pool:
        victim = pool.submit(key, text, long_spec.to_dict(), long_unit, tag=1)
        waiting = pool.submit(key, text, long_spec.to_dict(), long_unit, tag=2)
        after = pool.submit(key, text, small.to_dict(), small_unit, tag=3)
        wait_for(lambda: pool.rendering() == [1], 120, "the long unit rendering")
        assert pool.stop(2)  # still waiting: dropped
        assert waiting.cancelled()
        assert pool.stop(1)  # rendering: its process is killed
        with pytest.raises(UnitStopped):
            victim.result(30)
        # The slot starts a new process and renders the next unit (minutes
        # behind the long unit if it had not been stopped).
        assert PartialFilm.from_bytes(after.result(60)).stats["samples"] == 8 * 8 * 4
        assert not pool.stop(1) and not pool.stop(99)  # nothing has those tags now
