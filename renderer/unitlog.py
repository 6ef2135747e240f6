"""A unit's own log: the logging records emitted while it renders, and its
exception with traceback if it failed, captured in the process that renders it.

    with capture_unit_log(job_id="3f9c", index=7) as captured:
        film = execute_unit(...)
    captured.to_dict()   # {"lines": [...], "traceback": None, "dropped": 0}

On an exception the block re-raises it; `captured` holds its traceback. The
capture is bounded (the last `MAX_LINES` lines, `MAX_BYTES` in all; the count
of lines dropped is kept), so a unit that logs in a loop costs little. The
executors carry `to_dict()` back to the service, which keeps it per attempt.

The job and unit ids in force are a context variable (`unit_context`), so
`JsonLogFormatter` can put them on every record logged while a unit runs,
whoever logs it. Both live here, in the bottom layer, because the render
processes of the embedded pool and of Celery workers both import the renderer.
"""

from __future__ import annotations

import contextvars
import json
import logging
import os
import traceback
from collections import deque
from contextlib import contextmanager
from datetime import datetime, timezone
from typing import Iterator

__all__ = ["capture_unit_log", "CapturedLog", "unit_context", "JsonLogFormatter",
           "configure_logging", "MAX_LINES", "MAX_BYTES"]

MAX_LINES = 200
MAX_BYTES = 64 * 1024
_MAX_TRACEBACK = 32 * 1024  # a deep recursion's traceback is cut at its start, not its end

# (job_id, unit index) of the unit this thread renders, or None.
unit_context: contextvars.ContextVar[tuple[str | None, int | None] | None] = \
    contextvars.ContextVar("rayfarm_unit", default=None)

_LINE_FORMAT = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")


class CapturedLog(logging.Handler):
    """The bounded tail of one unit's log records, plus its traceback."""

    def __init__(self, max_lines: int = MAX_LINES, max_bytes: int = MAX_BYTES):
        super().__init__(logging.INFO)
        self.max_lines, self.max_bytes = max_lines, max_bytes
        self.lines: deque[str] = deque()
        self.size = 0
        self.dropped = 0
        self.traceback: str | None = None
        self.setFormatter(_LINE_FORMAT)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            line = self.format(record)[: self.max_bytes]
        except Exception:  # a bad format string must not fail the unit
            line = f"{record.levelname} {record.name}: {record.msg!r} (unformattable)"
        self.lines.append(line)
        self.size += len(line) + 1
        while len(self.lines) > self.max_lines or self.size > self.max_bytes:
            self.size -= len(self.lines.popleft()) + 1
            self.dropped += 1

    def note_exception(self, exc: BaseException) -> None:
        text = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
        self.traceback = text[-_MAX_TRACEBACK:]

    def to_dict(self) -> dict:
        """Plain data for any boundary (pickle, JSON)."""
        return {"lines": list(self.lines), "traceback": self.traceback, "dropped": self.dropped}


@contextmanager
def capture_unit_log(job_id: str | None = None, index: int | None = None,
                     max_lines: int = MAX_LINES, max_bytes: int = MAX_BYTES
                     ) -> Iterator[CapturedLog]:
    """Capture the INFO-and-above records of every logger while the block runs
    (see the module doc). The renderer's loggers are let down to INFO for the
    block if they were quieter, so its per-unit lines are always kept."""
    captured = CapturedLog(max_lines, max_bytes)
    root, ours = logging.getLogger(), logging.getLogger("renderer")
    quieter = ours.getEffectiveLevel() > logging.INFO
    if quieter:
        previous = ours.level
        ours.setLevel(logging.INFO)
    root.addHandler(captured)
    token = unit_context.set((job_id, index))
    try:
        yield captured
    except BaseException as exc:
        captured.note_exception(exc)
        raise
    finally:
        unit_context.reset(token)
        root.removeHandler(captured)
        if quieter:
            ours.setLevel(previous)


class JsonLogFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message, and `job_id` and
    `unit` when a unit is rendering (or the record carries them as `extra`)."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {"time": datetime.fromtimestamp(record.created, timezone.utc)
                 .isoformat(timespec="milliseconds"),
                 "level": record.levelname, "logger": record.name,
                 "message": record.getMessage()}
        job_id, index = getattr(record, "job_id", None), getattr(record, "unit", None)
        if job_id is None and index is None:
            job_id, index = unit_context.get() or (None, None)
        if job_id is not None:
            entry["job_id"] = job_id
        if index is not None:
            entry["unit"] = index
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


def configure_logging(level: int | str = logging.INFO, fmt: str | None = None) -> bool:
    """Make every handler of the root logger write JSON when `fmt` (default:
    `RAYFARM_LOG_FORMAT`) is "json", adding a stderr handler if there is none.
    Returns whether JSON is on. Other values leave the handlers as they are."""
    fmt = (fmt if fmt is not None else os.environ.get("RAYFARM_LOG_FORMAT", "")).strip().lower()
    if fmt != "json":
        return False
    root = logging.getLogger()
    if not root.handlers:
        root.addHandler(logging.StreamHandler())
    for handler in root.handlers:
        handler.setFormatter(JsonLogFormatter())
    root.setLevel(level if isinstance(level, int) else level.upper())
    return True
