"""The poll loop of every server-sent event stream (the API's ``/campaigns/{id}/events`` and the
dashboard's streams): look, send what changed, keep the connection alive, sleep."""

from __future__ import annotations

import asyncio
import time
from typing import AsyncIterator, Awaitable, Callable, Optional

KEEP_ALIVE = ": keep-alive\n\n"


async def poll(step: Callable[[], Awaitable[tuple[list[str], bool]]], interval_s: float, keepalive_s: float,
               connected: Optional[Callable[[], Awaitable[bool]]] = None) -> AsyncIterator[str]:
    """Every ``interval_s``: ``step()`` says what to send (events, already formatted) and whether
    the stream is done; after ``keepalive_s`` without an event, a comment keeps the connection
    open. Ends when ``step`` says so or ``connected()`` (checked before each look) says no."""
    last_sent = time.monotonic()
    while connected is None or await connected():
        chunks, done = await step()
        for chunk in chunks:
            yield chunk
        if chunks:
            last_sent = time.monotonic()
        elif time.monotonic() - last_sent > keepalive_s:
            yield KEEP_ALIVE
            last_sent = time.monotonic()
        if done:
            return
        await asyncio.sleep(interval_s)


class Changed:
    """Remembers the last value sent: ``changed(value)`` is true (and remembers it) when it differs."""

    def __init__(self) -> None:
        self.last: object = None

    def __call__(self, value: object) -> bool:
        if value == self.last:
            return False
        self.last = value
        return True
