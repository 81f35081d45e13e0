"""The Python API: campaigns in this process (``simulate``) or on a running orchestrator
(``Client``), returning the same results object as ``ra2vipas simulate --json`` and
``GET /campaigns/{id}/results``."""

from __future__ import annotations

import time
from typing import Any, Iterable, Mapping

import httpx


def _check_run(algorithms: Iterable[str] | None, tests: int, seed: int, stop_confidence: float, workers: int | None) -> list[str]:
    from ra2vipas.services.controller import registry

    if isinstance(algorithms, str):
        algorithms = [algorithms]
    names = registry.check(list(algorithms)) if algorithms is not None else list(registry.BUILTINS)  # UnknownPolicy is a ValueError
    from ra2vipas.services.protocol.messages import MAX_TESTS

    if isinstance(tests, bool) or not isinstance(tests, int) or not 1 <= tests <= MAX_TESTS:
        raise ValueError(f"tests: expected an integer from 1 to {MAX_TESTS}, got {tests!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed!r}")
    if isinstance(stop_confidence, bool) or not isinstance(stop_confidence, (int, float)) or not 0.0 <= stop_confidence < 1.0:
        raise ValueError(f"stop_confidence: expected a number in [0, 1), got {stop_confidence!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers: expected a positive integer, got {workers!r}")
    return names


def simulate(preset: str = "paper", overrides: Mapping[str, Any] | None = None, tests: int = 50, seed: int = 1,
             algorithms: Iterable[str] | None = None, stop_confidence: float = 0.0, workers: int | None = None) -> dict[str, Any]:
    """Run a Monte Carlo campaign in this process, like ``ra2vipas simulate --json``.

    Parameters
    ----------
    preset : str
        A scenario preset (``ra2vipas presets list``).
    overrides : mapping, optional
        Scenario parameters to override, e.g. ``{"n_targets": 30}`` (typed values).
    tests, seed : int
        Tests per algorithm and the campaign seed (fixes every random draw).
    algorithms : iterable of str, optional
        Default: all of ``ra2vipas``, ``rapas``, ``ravipas``, ``sweep``.
    stop_confidence : float
        0 (default): every episode runs to the horizon; else each ends at its first step that
        confident, its answer final, and the results gain ``decision`` blocks.
    workers : int, optional
        Worker processes (default 1 here; results are identical for any number). A script
        that uses more than one needs the usual ``if __name__ == "__main__":`` guard.

    Returns
    -------
    dict
        The results object (DR curves with Wilson bands, final DR, t90, in-FoV, POD R²,
        calibration), with ``outcomes`` (per algorithm, the final hit of every test) and
        ``paired`` (every pair of algorithms compared test by test: McNemar's exact test).

    Raises
    ------
    ValueError
        A bad preset, parameter, value or algorithm (one line naming it).
    """
    from ra2vipas.services.orchestrator.simulate import run_campaign
    from ra2vipas.services.protocol.scenario import build_scenario

    names = _check_run(algorithms, tests, seed, stop_confidence, workers)
    scenario = build_scenario(preset, dict(overrides or {}))  # ScenarioError is a ValueError
    return run_campaign(preset, scenario, tests, seed, names, stop_confidence=float(stop_confidence), workers=workers or 1)


def study(vary: Mapping[str, Iterable[Any]], preset: str = "paper", overrides: Mapping[str, Any] | None = None, tests: int = 50,
          seed: int = 1, algorithms: Iterable[str] | None = None, stop_confidence: float = 0.0,
          workers: int | None = None) -> dict[str, Any]:
    """A parameter study in this process, like ``ra2vipas simulate --vary ... --json``: one
    campaign per point of the grid ``vary`` ({parameter: values}; several parameters: their
    product), all with the same seed, so points are paired test by test.

    Returns the study's results object: ``rows`` has one row per point x algorithm (the varied
    values, final DR and its Wilson CI, t90, in-FoV, POD R², calibration fields); ``points``
    the grid. ``to_dataframe`` turns it into a table.

    Raises
    ------
    ValueError
        A bad preset, parameter, value or grid (one line naming it).
    """
    from ra2vipas.services.orchestrator.engine import run_study

    names = _check_run(algorithms, tests, seed, stop_confidence, workers)
    if not isinstance(vary, Mapping) or not vary:
        raise ValueError("vary: expected a mapping {parameter: [values]} with at least one parameter")
    grid = {str(k): list(v) for k, v in vary.items()}
    return run_study(preset, dict(overrides or {}), grid, tests, seed, names, float(stop_confidence), workers=workers or 1)


def paired_test(hits_a: Iterable[Any], hits_b: Iterable[Any], a: str = "a", b: str = "b") -> dict[str, Any]:
    """Two algorithms' final answers compared test by test (McNemar's exact test), e.g. on a
    results object's ``outcomes`` (``results["paired"]`` has every pair of its algorithms
    already) or on the same algorithm in two campaigns with the same seed (test k meets the
    world drawn from (seed, k) in both, changed only by what differs).

    Parameters
    ----------
    hits_a, hits_b : iterables of 1/0 (or bool), None for a test not recorded
        The final hit of each test, by test index.
    a, b : str
        Names for the two sides.

    Returns
    -------
    dict
        ``tests`` (both recorded), ``both``, ``only_a``, ``only_b``, ``neither``,
        ``dr_difference`` (DR of a minus b on those tests) and ``p_value`` (two-sided exact
        binomial test of ``only_a`` among the discordant tests, p = 1/2).
    """
    from ra2vipas.services.orchestrator.metrics import paired_comparison

    return paired_comparison(a, list(hits_a), b, list(hits_b))


class ClientError(Exception):
    """A request to the orchestrator failed; ``status`` is the HTTP status (None: unreachable)."""

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


FINISHED = ("done", "failed", "cancelled")


class Client:
    """A client of the orchestrator's REST API (``ra2vipas up``, or a deployment).

    Parameters
    ----------
    api : str
        Base URL, e.g. ``http://127.0.0.1:8080``.
    token : str, optional
        Bearer token of a server started with one (needed to start, cancel or delete).
    """

    def __init__(self, api: str = "http://127.0.0.1:8080", token: str | None = None, timeout: float = 30.0) -> None:
        self.api = api.rstrip("/")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=self.api, headers=headers, timeout=timeout)

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *_exc) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _request(self, method: str, path: str, **kw) -> Any:
        try:
            r = self._http.request(method, path, **kw)
        except httpx.HTTPError as err:
            raise ClientError(f"cannot reach the API at {self.api}: {type(err).__name__}") from None
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text[:200]
            raise ClientError(f"{method} {path}: HTTP {r.status_code}: {detail}", r.status_code)
        return None if r.status_code == 204 or not r.content else r.json()

    # -- campaigns ---------------------------------------------------------------------------
    def start_campaign(self, preset: str = "paper", overrides: Mapping[str, Any] | None = None, tests: int = 50, seed: int = 1,
                       algorithms: Iterable[str] | None = None, mode: str = "fast", name: str | None = None,
                       **options: Any) -> dict[str, Any]:
        """Create a campaign (``POST /campaigns``); returns it (``id``, ``status``, ...).
        Further campaign options of the API (e.g. ``stop_confidence``) pass through ``options``."""
        body: dict[str, Any] = {"preset": preset, "overrides": dict(overrides or {}), "tests": tests, "seed": seed, "mode": mode,
                                **options}
        if algorithms is not None:
            body["algorithms"] = list(algorithms)
        if name is not None:
            body["name"] = name
        return self._request("POST", "/campaigns", json=body)

    def campaign(self, campaign_id: str) -> dict[str, Any]:
        return self._request("GET", f"/campaigns/{campaign_id}")

    def campaigns(self, **filters: Any) -> list[dict[str, Any]]:
        """Every campaign matching the filters (``status``, ``preset``), newest first."""
        out, offset = [], 0
        while True:
            page = self._request("GET", "/campaigns", params={**filters, "limit": 200, "offset": offset})
            out += page["items"]
            offset += len(page["items"])
            if not page["items"] or offset >= page["total"]:
                return out

    def results(self, campaign_id: str) -> dict[str, Any]:
        return self._request("GET", f"/campaigns/{campaign_id}/results")

    def cancel(self, campaign_id: str) -> dict[str, Any]:
        return self._request("POST", f"/campaigns/{campaign_id}/cancel")

    def delete(self, campaign_id: str) -> None:
        self._request("DELETE", f"/campaigns/{campaign_id}")

    # -- studies ------------------------------------------------------------------------------
    def start_study(self, vary: Mapping[str, Iterable[Any]], preset: str = "paper", overrides: Mapping[str, Any] | None = None,
                    tests: int = 50, seed: int = 1, algorithms: Iterable[str] | None = None, mode: str = "fast",
                    name: str | None = None, **options: Any) -> dict[str, Any]:
        """Create a parameter study (``POST /studies``); returns it (``id``, ``status``, points)."""
        body: dict[str, Any] = {"preset": preset, "overrides": dict(overrides or {}), "vary": {k: list(v) for k, v in vary.items()},
                                "tests": tests, "seed": seed, "mode": mode, **options}
        if algorithms is not None:
            body["algorithms"] = list(algorithms)
        if name is not None:
            body["name"] = name
        return self._request("POST", "/studies", json=body)

    def study(self, study_id: str) -> dict[str, Any]:
        return self._request("GET", f"/studies/{study_id}")

    def study_results(self, study_id: str) -> dict[str, Any]:
        return self._request("GET", f"/studies/{study_id}/results")

    def cancel_study(self, study_id: str) -> dict[str, Any]:
        return self._request("POST", f"/studies/{study_id}/cancel")

    def delete_study(self, study_id: str) -> None:
        self._request("DELETE", f"/studies/{study_id}")

    def wait_study(self, study_id: str, timeout: float | None = None, poll: float = 0.5) -> dict[str, Any]:
        """Wait for a study to finish and return its results object (``ClientError`` if it
        failed, was cancelled, or ``timeout`` seconds passed)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            s = self.study(study_id)
            if s["status"] == "done":
                return self.study_results(study_id)
            if s["status"] in FINISHED:
                raise ClientError(f"study {study_id} {s['status']}: {s.get('error') or ''}".rstrip(": "))
            if deadline is not None and time.monotonic() > deadline:
                raise ClientError(f"study {study_id} did not finish within {timeout} s")
            time.sleep(poll)

    def wait(self, campaign_id: str, timeout: float | None = None, poll: float = 0.5) -> dict[str, Any]:
        """Wait for a campaign to finish and return its results object.

        Raises
        ------
        ClientError
            It failed or was cancelled, or ``timeout`` seconds passed.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            c = self.campaign(campaign_id)
            if c["status"] == "done":
                return self.results(campaign_id)
            if c["status"] in FINISHED:
                raise ClientError(f"campaign {campaign_id} {c['status']}: {c.get('error') or ''}".rstrip(": "))
            if deadline is not None and time.monotonic() > deadline:
                raise ClientError(f"campaign {campaign_id} did not finish within {timeout} s")
            time.sleep(poll)


def to_dataframe(results: Mapping[str, Any]):
    """A results object as a tidy pandas DataFrame (needs pandas: ``pip install
    'ra2vipas[pandas]'``): a campaign's, one row per (algorithm, step) with time, DR and its
    Wilson band, led by what was run (preset, seed, tests, one column per override: the CSV
    ``dr`` table); a study's, its ``rows`` (one per point x algorithm) with the columns of
    ``ra2vipas study results ID --csv`` in the same order, in this process or through ``Client``."""
    try:
        import pandas as pd
    except ImportError:
        raise ImportError("to_dataframe needs pandas: pip install 'ra2vipas[pandas]'") from None
    if "rows" in results and "points" in results:  # a study: the CSV's columns, in the CSV's order
        from ra2vipas.services.orchestrator.study import study_columns, table_rows

        return pd.DataFrame(table_rows(results), columns=study_columns(results))
    from ra2vipas.services.orchestrator.api.export import curve_rows

    return pd.DataFrame(curve_rows(dict(results)))
