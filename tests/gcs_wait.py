"""Waiting for a message a test's fake ground station received (test_signing, the mock's
behaviour tests): one scan of the received list, woken by the protocol's event."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from typing import Any


async def first_message(received: Sequence[Any], new: asyncio.Event,
                        pred: Callable[[Any], bool], *, since: int = 0, timeout: float = 10.0,
                        what: str = "", message: Callable[[Any], Any] = lambda e: e) -> Any:
    """The first ``message(received[i])`` with ``i >= since`` satisfying ``pred``, waiting
    (``new`` is set on every datagram) up to ``timeout`` s; AssertionError naming ``what``."""
    i = since

    async def scan() -> Any:
        nonlocal i
        while True:
            while i < len(received):
                m = message(received[i])
                i += 1
                if pred(m):
                    return m
            new.clear()
            await new.wait()

    try:
        return await asyncio.wait_for(scan(), timeout)
    except TimeoutError:
        raise AssertionError(f"no {what or 'matching message'} within {timeout} s") from None
