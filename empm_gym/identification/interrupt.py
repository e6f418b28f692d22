"""Stop a long fit at a clean point on Ctrl-C (SIGINT) or SIGTERM.

    with stop_on_signals() as stop:
        res = identify(obs, scene, stop=stop)  # checks stop.is_set() before every iteration
    if stop.is_set():
        ...  # stop.signum: the signal received; stop.exit_code: 128 + signum

The first signal only sets the request, so the fit finishes its current iteration and returns what it has.
A second signal while stopping raises ``KeyboardInterrupt`` at once (a hard stop). On exit the previous
handlers are restored. Python installs signal handlers only in the main thread: elsewhere nothing is
installed and the request is set only by calling :meth:`StopRequest.set`.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator, Optional, Sequence

__all__ = ["StopRequest", "stop_on_signals"]


class StopRequest:
    """A flag that a signal handler (or any caller) sets to ask a fit to stop after its current iteration.

    It deliberately holds no lock (unlike ``threading.Event``): a signal handler runs in the main thread
    between two bytecodes and must never wait for a lock that thread may hold.
    """

    def __init__(self) -> None:
        self._set = False
        self.signum: Optional[int] = None

    def set(self, signum: Optional[int] = None) -> None:
        """Request the stop (``signum``: the signal that asked for it, if any)."""
        if not self._set:
            self.signum = signum
        self._set = True

    def is_set(self) -> bool:
        """Whether a stop was requested."""
        return self._set

    def __call__(self) -> bool:
        return self._set

    @property
    def signal_name(self) -> str:
        """"SIGINT", "SIGTERM", ... ("stop request" when set by a call)."""
        return signal.Signals(self.signum).name if self.signum is not None else "stop request"

    @property
    def exit_code(self) -> int:
        """The shell's code for death by the signal (130 for SIGINT, 143 for SIGTERM); 1 when set by a call."""
        return 128 + int(self.signum) if self.signum is not None else 1


@contextmanager
def stop_on_signals(signals: Sequence[int] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[StopRequest]:
    """Install handlers for ``signals`` that set a :class:`StopRequest` (yielded); restore the previous
    handlers on exit. A second signal raises ``KeyboardInterrupt``."""
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt(f"{signal.Signals(signum).name} while stopping")
        stop.set(signum)

    previous = {}
    try:
        for s in signals:
            previous[s] = signal.signal(s, handler)
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
