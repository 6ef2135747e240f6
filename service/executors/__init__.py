"""Executors run work units: the embedded process pool or the Celery farm.

Both have one interface (`Executor`), used by the scheduler thread only:
`submit` a `Ticket`, `observe` the units in flight, `release` what was
stored, `cancel` what is no longer wanted and `stop` a unit preempted or
over its time budget (both end a running unit too), and say how many more units to
send (`capacity`: each keeps little beyond what it can run at once). `make_executor(settings, ...)`
picks one: Celery when `broker_url` is set, else the local pool.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from ..settings import Settings
from .base import Executor, Flight, Observation, RunningUnit, Ticket, WorkerInfo

__all__ = ["Executor", "Flight", "Observation", "RunningUnit", "Ticket", "WorkerInfo",
           "make_executor"]


def make_executor(settings: Settings, load_scene_text: Callable[[str], str],
                  load_unit_film: Callable[[str, int], bytes] | None = None,
                  asset_dir: Path | None = None) -> Executor:
    """The executor `settings` ask for; `load_scene_text(hash)` and
    `load_unit_film(job_id, index)` read the store (a DAG unit's inputs);
    `asset_dir` is the store's folder of assets (`<digest>` files), which
    the scenes' meshes and textures are read from."""
    if settings.broker_url:
        from .celery_farm import CeleryExecutor

        return CeleryExecutor(settings, load_scene_text, load_unit_film, asset_dir=asset_dir)
    from .local import LocalExecutor

    return LocalExecutor(settings, load_scene_text, load_unit_film, asset_dir=asset_dir)
