"""A node that speaks protocol 1.0 and nothing newer, built from the frozen schemas.

``StrictV1Bus`` wraps the bus a node is given: every payload the node receives (a sample it
subscribed to, a query it serves, a reply to its query) is validated against the 1.0 JSON
Schema of its key (``docs/schemas/v1``, with ``additionalProperties: false``: "Unknown fields
are rejected", as the 1.0 page said) and dropped when it does not validate, as a node written
from that page alone does; every payload it sends may be checked too. Whatever was dropped or
sent out of schema is kept in ``rejected`` and ``violations``.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

from jsonschema import Draft202012Validator

from ra2vipas.services.transport.bus import Reply

ROOT = Path(__file__).resolve().parents[2]
V1_SCHEMAS = ROOT / "docs" / "schemas" / "v1"


def v1_validator(name: str) -> Draft202012Validator:
    return Draft202012Validator(json.loads((V1_SCHEMAS / f"{name}.json").read_text()))


def v1_errors(name: str, payload: bytes) -> list[str]:
    """Why ``payload`` is not a 1.0 ``name`` message (empty: it is)."""
    try:
        doc = json.loads(payload)
    except ValueError as err:
        return [f"not JSON: {err}"]
    return [f"{'/'.join(map(str, e.absolute_path)) or '.'}: {e.message}" for e in v1_validator(name).iter_errors(doc)]


# the 1.0 message of each key family (keys.py), as (published or query payload, reply)
V1_KEYS = {
    ("control", "episode"): ("EpisodeControl", None),
    ("data", "command"): ("Command", None),
    ("data", "measurement"): ("Measurement", None),
    ("data", "training"): ("TrainingRequest", "TrainingStream"),
    ("truth", "episode"): ("EpisodeTruth", None),
    ("truth", "training"): ("TrainingRequest", "TrainingTruth"),
    ("result", "episode"): ("EpisodeResult", None),
    ("result", "timing"): ("EpisodeTiming", None),
    ("model", "pod"): ("PODRequest", "PODResponse"),
}


def v1_schema_of(key: str, reply: bool = False) -> str | None:
    """The 1.0 message on ``key`` (or in a reply to a query on it); None: not a 1.0 key."""
    parts = key.split("/")
    family = (parts[2], parts[-1]) if len(parts) >= 4 else None
    names = V1_KEYS.get(family)  # type: ignore[arg-type]
    return None if names is None else names[1 if reply else 0]


class _Undeclared:
    def undeclare(self) -> None:
        pass


class StrictV1Bus:
    """The bus as a 1.0 node sees it (see the module docstring). ``check_sent``: also record
    what the node sends that a 1.0 receiver would reject; ``as_v1_request``: rewrite the
    node's outgoing query payloads to what a 1.0 node sends (a function of key and payload)."""

    def __init__(self, bus, check_sent: bool = True, as_v1_request=None) -> None:
        self.bus = bus
        self.check_sent = check_sent
        self.as_v1_request = as_v1_request
        self.rejected: list[str] = []
        self.violations: list[str] = []
        self._lock = threading.Lock()

    def _accept(self, key: str, payload: bytes, reply: bool = False) -> bool:
        name = v1_schema_of(key, reply)
        errors = [f"{key}: no such key in protocol 1.0"] if name is None else v1_errors(name, payload)
        if errors:
            with self._lock:
                self.rejected.append(f"dropped a {name} message on {key}: {errors[0]}")
        return not errors

    def _sent(self, key: str, payload: bytes, reply: bool = False) -> None:
        if not self.check_sent:
            return
        name = v1_schema_of(key, reply)
        errors = [f"{key}: no such key in protocol 1.0"] if name is None else v1_errors(name, payload)
        if errors:
            with self._lock:
                self.violations.append(f"sent a {name} message on {key} that 1.0 rejects: {errors[0]}")

    def publish(self, key: str, payload: bytes, express: bool = False) -> None:
        self._sent(key, payload)
        self.bus.publish(key, payload, express)

    def subscribe(self, key: str, callback):
        return self.bus.subscribe(key, lambda k, p: callback(k, p) if self._accept(k, p) else None)

    def serve(self, key: str, handler):
        if v1_schema_of(key) is None:  # a 1.0 node serves nothing on a newer key (e.g. rig/{rig}/policies)
            return _Undeclared()

        def strict(k: str, payload: bytes) -> bytes:
            if not self._accept(k, payload):
                from ra2vipas.services.transport.bus import QueryError

                raise QueryError("malformed request")
            out = handler(k, payload)
            self._sent(k, out, reply=True)
            return out

        return self.bus.serve(key, strict)

    def query(self, key: str, payload: bytes, timeout: float, callback) -> None:
        if self.as_v1_request is not None:
            payload = self.as_v1_request(key, payload)
        if v1_schema_of(key) is None:  # a 1.0 node never asks anything on a newer key
            threading.Thread(target=callback, args=([],), daemon=True).start()
            return
        self._sent(key, payload)

        def strict(replies: list[Reply]) -> None:
            callback([r for r in replies if not r.ok or self._accept(key, r.payload, reply=True)])

        self.bus.query(key, payload, timeout, strict)

    def announce(self, key: str):
        return self.bus.announce(key)

    def watch_alive(self, key: str, callback):
        return self.bus.watch_alive(key, callback)

    def close(self) -> None:
        pass
