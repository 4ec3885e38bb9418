"""SIGINT / SIGTERM for the commands: the library exposes ``interrupt``, this installs it."""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import Callable, Iterator

__all__ = ["interrupt_on_signals"]


@contextlib.contextmanager
def interrupt_on_signals(callback: Callable[[str], None]) -> Iterator[None]:
    """While inside: SIGINT and SIGTERM call ``callback("SIGINT" | "SIGTERM")`` on the running
    event loop instead of raising :class:`KeyboardInterrupt`."""
    loop = asyncio.get_running_loop()
    installed: list[signal.Signals] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, callback, sig.name)
            installed.append(sig)
        except (NotImplementedError, RuntimeError, ValueError):  # not the main thread
            pass
    try:
        yield
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)
