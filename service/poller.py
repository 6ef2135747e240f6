"""A thread that reads the ledger every few seconds while there is a reason to.

    class Watch(Poller):
        what = "my watch"
        def wanted(self): return bool(self.hub.subscribers)
        def poll(self): ...

`poll()` runs every `interval` seconds while `wanted()`; in between, `idle()`
forgets what a poll remembered (the first poll after a pause starts afresh).
A poll that raises (the ledger busy, a connection dropped) is logged and the
next one tries again: a watch never dies of one failure.
"""

from __future__ import annotations

import logging
import threading

__all__ = ["Poller"]

log = logging.getLogger(__name__)


class Poller:
    what = "poller"  # the thread's name and its log lines'

    def __init__(self, interval: float):
        self.interval = interval
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.polls = 0

    def wanted(self) -> bool:
        return True

    def idle(self) -> None:
        """A round without a poll (`wanted()` false)."""

    def poll(self) -> None:
        raise NotImplementedError

    def try_poll(self) -> None:
        try:
            self.poll()
        except Exception as exc:  # the ledger may be busy; the next round tries again
            log.warning("%s: %s: %s", self.what, type(exc).__name__, exc)

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, daemon=True,
                                        name="rayfarm-" + self.what.replace(" ", "-"))
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
            self._thread = None

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            if self.wanted():
                self.try_poll()
            else:
                self.idle()
