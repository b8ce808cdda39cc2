"""SIGINT and SIGTERM as a request to stop cleanly, not a crash that loses the run's work.

A mapping run interrupted with Ctrl-C, ``kill``, ``systemctl stop`` or ``docker stop`` should
still leave a map of what it saw (slam_toolbox users serialise by hand before killing the node
for this). :class:`StopSignals` turns the first signal into a flag the run polls between
frames; the run then finishes its work and writes its outputs as usual. A second signal means
"now": the previous handlers come back and KeyboardInterrupt is raised (the CLI prints
"interrupted", exit 130). Handlers can only be set from the main thread; elsewhere (a batch
worker) the object only holds a flag that nobody sets.
"""

from __future__ import annotations

import logging
import signal
import threading
from types import FrameType, TracebackType
from typing import Any

log = logging.getLogger(__name__)

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopSignals:
    """Context manager: ``event`` is set by the first SIGINT/SIGTERM; ``signum`` says which.

    ``message`` is logged as a warning when the first signal arrives; with ``second_aborts``
    a second one raises KeyboardInterrupt, otherwise it is logged again and ignored.
    """

    def __init__(
        self,
        message: str,
        event: threading.Event | None = None,
        second_aborts: bool = True,
    ) -> None:
        self.message, self.second_aborts = message, second_aborts
        self.event = event if event is not None else threading.Event()
        self.signum: int | None = None
        self._old: dict[int, Any] = {}

    @property
    def name(self) -> str | None:
        """The first signal's name (``"SIGTERM"``), or None before one."""
        return None if self.signum is None else signal.Signals(self.signum).name

    def is_set(self) -> bool:
        return self.event.is_set()

    def _handler(self, signum: int, _frame: FrameType | None) -> None:
        if self.signum is not None and self.second_aborts:
            self._restore()
            raise KeyboardInterrupt
        self.signum = signum if self.signum is None else self.signum
        log.warning("%s: %s", signal.Signals(signum).name, self.message)
        self.event.set()

    def _restore(self) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old = {}

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            self._old = {s: signal.getsignal(s) for s in SIGNALS}
            for s in SIGNALS:
                signal.signal(s, self._handler)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._restore()

    def record(self, summary: dict[str, Any], read: int, total: int, what: str = "scans") -> None:
        """After a run's reading loop: if a signal stopped it, say so in the run's summary
        (``interrupted``: the signal, the scans or frames read, of how many) and in the log."""
        if self.signum is None:
            return
        summary["interrupted"] = {"signal": self.name, f"{what}_read": read, "of": total}
        log.warning("%s: finishing with the %d of %d %s read", self.name, read, total, what)

    @property
    def exit_code(self) -> int:
        """The shell's code for a run ended by this signal (130 SIGINT, 143 SIGTERM); 0 if none."""
        return 0 if self.signum is None else 128 + self.signum


__all__ = ["StopSignals"]
