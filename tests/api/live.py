"""A live orchestrator for API and CLI tests: the real FastAPI app served by a real uvicorn
server on a loopback port, backed by a real SQLite file, with the real sensors, controller
and learner nodes on the same in-memory bus (the mesh without Zenoh).

``LiveAPI.stop()`` shuts the server down (lifespan: scheduler, bus, store) and closes every
node; tests use it through fixtures so every thread they start is stopped.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import uvicorn

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.learner.node import LearnerNode
from ra2vipas.services.orchestrator.api.app import create_app
from ra2vipas.services.orchestrator.settings import OrchestratorSettings
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.transport.bus import MemoryBus

# A scenario small enough that a campaign of a few tests takes about a second.
SMALL = {"steps": 20, "n_train": 200, "n_targets": 8}


class LiveAPI:
    def __init__(self, db_path: Path | str, *, rigs: tuple[str, ...] = ("rig-1",), learner: bool = True,
                 token: str | None = None, window: int = 4, plot_rate: float = 10000.0,
                 sensors: dict[str, dict] | None = None, controllers: dict[str, dict] | None = None) -> None:
        """``sensors``: keyword arguments of a rig's ``SensorsNode`` (its descriptor, ``describe``);
        ``controllers``: of its ``ControllerNode`` (``policies``, the ones it serves)."""
        self.db_path = str(db_path)
        self.bus = MemoryBus()
        self.nodes: list = []
        for rig in rigs:
            self.nodes += [SensorsNode(self.bus, rig, **(sensors or {}).get(rig, {})), ControllerNode(self.bus, rig, **(controllers or {}).get(rig, {}))]
        if learner:
            self.nodes.append(LearnerNode(self.bus))
        settings = OrchestratorSettings(host="127.0.0.1", port=0, db_path=self.db_path, window=window, expect_rigs=len(rigs),
                                        token=token, plot_rate=plot_rate)  # high by default: the rate limit has its own test
        self.app = create_app(settings, bus_factory=lambda: self.bus)
        config = uvicorn.Config(self.app, host="127.0.0.1", port=0, log_level="warning", lifespan="on",
                                timeout_graceful_shutdown=2, timeout_keep_alive=2)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="uvicorn-test", daemon=True)
        self.url = ""

    def start(self, timeout: float = 20.0) -> "LiveAPI":
        self.thread.start()
        deadline = time.monotonic() + timeout
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError("the test API server did not start")
            time.sleep(0.02)
        port = self.server.servers[0].sockets[0].getsockname()[1]
        self.url = f"http://127.0.0.1:{port}"
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        if self.thread.is_alive():
            self.thread.join(20.0)
        for node in self.nodes:
            node.close()
        self.bus.close()
        assert not self.thread.is_alive(), "the test API server did not stop"

    def settle(self, rounds: int = 3) -> None:
        """Wait until the bus, every node and the scheduler have handled what was sent so far."""
        loops = [node.loop for node in self.nodes if hasattr(node, "loop")] + [self.scheduler.loop]

        def drain() -> None:
            self.bus.wait_idle()
            for loop in loops:
                assert loop.wait_idle(), "a node's event loop did not drain"

        for _ in range(rounds):
            drain()
        # a v1 node's silence is taken as such once the scheduler asked again (DESCRIPTOR_REASK_S)
        deadline = time.monotonic() + 10.0
        while any("asking" in (rig.described, rig.announced) for rig in list(self.scheduler.rigs.values())):
            assert time.monotonic() < deadline, "the scheduler still asks a rig what it is"
            time.sleep(0.05)
        drain()

    @property
    def scheduler(self):
        return self.app.state.scheduler

    def client(self, token: str | None = None) -> httpx.Client:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=30.0)

    def wait(self, cid: str, statuses=("done", "failed", "cancelled"), timeout: float = 120.0) -> dict:
        """Poll until the campaign reaches one of ``statuses``; return it."""
        deadline = time.monotonic() + timeout
        with self.client() as http:
            while time.monotonic() < deadline:
                c = http.get(f"/campaigns/{cid}").json()
                if c["status"] in statuses:
                    return c
                time.sleep(0.05)
        raise AssertionError(f"campaign {cid} did not reach {statuses}: {c}")
