"""SIGINT / SIGTERM / SIGHUP for the commands: the library exposes ``interrupt``, this installs
it."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import stat
import sys
from collections.abc import Callable, Iterator

__all__ = ["interrupt_on_signals"]


def _detach_from_terminal() -> None:
    """The terminal hung up: standard output and error that went to it go to /dev/null from
    now on (a write to a terminal that is gone fails with EIO; the summary keeps the events)."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(AttributeError, OSError, ValueError):
                fd = stream.fileno()
                # a terminal is a character device (isatty fails once it has hung up)
                if stat.S_ISCHR(os.fstat(fd).st_mode):
                    with contextlib.suppress(OSError):
                        stream.flush()
                    os.dup2(devnull, fd)
    finally:
        os.close(devnull)


@contextlib.contextmanager
def interrupt_on_signals(callback: Callable[[str], None]) -> Iterator[None]:
    """While inside: SIGINT and SIGTERM call ``callback("SIGINT" | "SIGTERM")`` on the running
    event loop instead of raising :class:`KeyboardInterrupt` (or ending the process at once).

    SIGHUP too (the operator's terminal or SSH session closed: by default the process would
    end on the spot and leave its vehicles to PX4's offboard-loss failsafe), unless it is
    ignored (``nohup``: the user asked to fly on); the output that went to the terminal is
    sent to /dev/null first."""
    loop = asyncio.get_running_loop()
    installed: list[signal.Signals] = []

    def hangup() -> None:
        _detach_from_terminal()
        callback("SIGHUP")

    handlers: list[tuple[signal.Signals, Callable[[], None]]] = [
        (signal.SIGINT, lambda: callback("SIGINT")),
        (signal.SIGTERM, lambda: callback("SIGTERM")),
    ]
    hup = getattr(signal, "SIGHUP", None)
    if hup is not None and signal.getsignal(hup) is not signal.SIG_IGN:
        handlers.append((hup, hangup))
    for sig, handler in handlers:
        try:
            loop.add_signal_handler(sig, handler)
            installed.append(sig)
        except (NotImplementedError, RuntimeError, ValueError):  # not the main thread
            pass
    try:
        yield
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)
