"""``get``, ``post``, ``put``, ``delete`` as ``httpx.get`` & co. take them, on one client.

Each ``httpx.get`` builds a client whose TLS context loads the CA bundle: ~75 ms of CPU, even for
an ``http://`` address, paid again by every poll of a loop that waits for a campaign or a health
answer (a 20 s wait polled every 0.1 s: 15 s of CPU). One client for the process instead, keeping
no connection alive between requests (each opens and closes its own, as ``httpx.get`` does: the
servers tests talk to come and go, and restart on the same ports)."""

from __future__ import annotations

import threading

import httpx

_client: httpx.Client | None = None
_lock = threading.Lock()


def client() -> httpx.Client:
    global _client
    with _lock:
        if _client is None:
            _client = httpx.Client(limits=httpx.Limits(max_keepalive_connections=0))
        return _client


def get(url: str, **kwargs) -> httpx.Response:
    return client().get(url, **kwargs)


def post(url: str, **kwargs) -> httpx.Response:
    return client().post(url, **kwargs)


def put(url: str, **kwargs) -> httpx.Response:
    return client().put(url, **kwargs)


def delete(url: str, **kwargs) -> httpx.Response:
    return client().delete(url, **kwargs)
