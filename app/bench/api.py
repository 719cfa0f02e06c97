"""``hrc bench api``: what the server costs the control loop, and how fast REST answers.

A real server (uvicorn on a free loopback port, one worker, the real runtime on the simulated cell, SQLite in
a temporary directory) runs a trial started over REST. Then, in alternating blocks (so that a change of
machine load hits both conditions alike), the control loop's ``frame_to_decision_ms`` is sampled with 0 and
with 20 live WebSocket clients on ``/api/live`` (the clients run in another process, as browsers would).
Finally a client process sends ``GET /api/robot`` at 50 requests per second and measures each answer.

Prints: ``frame_to_decision_ms`` (``p50``, ``p95``, ``n``) per condition, ``live_clients_overhead`` (p95 with
20 clients / p95 with 0), the live message rate per client, and REST ``p50_ms``/``p95_ms``/``max_ms``.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import secrets
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from app.bench.served import free_port

logger = logging.getLogger(__name__)

LIVE_CLIENTS = 20
REST_RATE_HZ = 50.0
REST_ROUTE = "/api/robot"


def _pct(samples: list[float], q: float) -> float | None:
    return float(np.percentile(np.asarray(samples), q)) if samples else None


def _stats(samples: list[float]) -> dict[str, Any]:
    return {
        "p50": _pct(samples, 50),
        "p95": _pct(samples, 95),
        "mean": float(statistics.fmean(samples)) if samples else None,
        "n": len(samples),
    }


# ---- client processes (spawned: no threads of the server are inherited) ------------------------------


def _live_clients_main(url: str, n: int, ready: Any, stop: Any, counts: Any) -> None:
    """Open ``n`` WebSocket clients on ``url`` and read until ``stop`` is set; ``counts[i]`` = messages."""
    import asyncio

    from websockets.asyncio.client import connect

    async def one(i: int, opened: asyncio.Event, n_open: list[int]) -> None:
        async with connect(url, max_size=2**22, open_timeout=20) as ws:
            n_open[0] += 1
            if n_open[0] == n:
                opened.set()
            while not stop.is_set():
                try:
                    await asyncio.wait_for(ws.recv(), timeout=0.5)
                except TimeoutError:
                    continue
                counts[i] += 1

    async def main() -> None:
        opened = asyncio.Event()
        n_open = [0]
        tasks = [asyncio.create_task(one(i, opened, n_open)) for i in range(n)]
        await asyncio.wait_for(opened.wait(), timeout=60)
        ready.set()
        await asyncio.gather(*tasks, return_exceptions=True)

    asyncio.run(main())


def _rest_client_main(base: str, token: str, n: int, rate_hz: float, out: Any) -> None:
    """Send ``n`` GETs paced at ``rate_hz`` (absolute deadlines); put the latencies (ms) into ``out``."""
    import httpx

    latencies: list[float] = []
    errors = 0
    period_s = 1.0 / rate_hz
    with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=10.0) as client:
        client.get(REST_ROUTE)  # connect and warm up
        t_next = time.perf_counter()
        for _ in range(n):
            now = time.perf_counter()
            if t_next > now:
                time.sleep(t_next - now)
            t0 = time.perf_counter()
            r = client.get(REST_ROUTE)
            latencies.append((time.perf_counter() - t0) * 1e3)
            errors += r.status_code != 200
            t_next += period_s
    out.put({"latencies_ms": latencies, "errors": errors})


# ---- the server under test --------------------------------------------------------------------------


class _Served:
    """The app under uvicorn on a background thread (started and stopped as a context manager)."""

    def __init__(self, settings: Any) -> None:
        import uvicorn

        from app.api.app import create_app

        self.app = create_app(settings, scene=False)
        self.server = uvicorn.Server(
            uvicorn.Config(
                self.app, host="127.0.0.1", port=settings.port, log_level="warning", lifespan="on", workers=1
            )
        )
        self.thread = threading.Thread(target=self.server.run, name="bench-uvicorn", daemon=True)

    def __enter__(self) -> _Served:
        self.thread.start()
        deadline = time.monotonic() + 300.0  # the first start may build the roadmap cache
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the server did not start (see the log above)")
            time.sleep(0.05)
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(60.0)


def _drain(samples: Any) -> list[float]:
    """Take (and remove) every sample of a runtime ``deque`` appended so far (others may keep appending)."""
    out = []
    for _ in range(len(samples)):
        try:
            out.append(float(samples.popleft()))
        except IndexError:
            break
    return out


def _loop_samples(runtime: Any) -> tuple[list[float], list[float]]:
    """(frame-to-decision ms, whole frame tick ms) that the runtime measured since the last call.

    Frame to decision: the supervisor's decision on a new frame (``Runtime.stats.decide_ms``; the backup
    plan's search runs on the planner pool and is not in it). Frame tick: the whole camera-rate tick (source,
    prediction, decision, snapshot and its publication; ``Runtime.stats.frame_ms``).
    """
    return _drain(runtime.stats.decide_ms), _drain(runtime.stats.frame_ms)


def run(*, quick: bool, progress: bool) -> dict[str, Any]:
    """Measure (see the module docstring); ``quick`` shortens every phase."""
    import httpx

    from app.config import Settings

    blocks = 2 if quick else 6
    block_s = 3.0 if quick else 6.0
    rest_n = 100 if quick else 500
    token = secrets.token_urlsafe(24)
    load_start = os.getloadavg()[0]
    ctx = mp.get_context("spawn")
    log = print if progress else (lambda *a, **k: None)
    with tempfile.TemporaryDirectory(prefix="hrc-bench-api-") as tmp:
        settings = Settings(
            _env_file=None,
            data_dir=Path(tmp),
            api_token=token,
            database_url=f"sqlite:///{Path(tmp) / 'bench.db'}",
            port=free_port(),
            robot="sim",
            human_source="sim",
        )
        base = f"http://127.0.0.1:{settings.port}"
        log(f"starting the server on {base} ...")
        with (
            _Served(settings) as served,
            httpx.Client(base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=30.0) as http,
        ):
            runtime = served.app.state.hrc.runtime
            p = http.post("/api/participants", json={"code": "bench"}).json()
            duration_s = blocks * 2 * (block_s + 5.0) + rest_n / REST_RATE_HZ + 60.0
            trial = http.post(
                "/api/trials",
                json={"participant_id": p["id"], "method": "proactive", "duration_s": duration_s, "seed": 1},
            )
            trial.raise_for_status()
            trial_id = trial.json()["id"]
            time.sleep(min(2.0, block_s))  # let the trial settle
            samples: dict[int, list[float]] = {0: [], LIVE_CLIENTS: []}
            ticks: dict[int, list[float]] = {0: [], LIVE_CLIENTS: []}
            live_rates: list[float] = []
            for b in range(blocks):
                order = (0, LIVE_CLIENTS) if b % 2 == 0 else (LIVE_CLIENTS, 0)
                for n_clients in order:
                    proc = stop = counts = None
                    if n_clients:
                        ready, stop = ctx.Event(), ctx.Event()
                        counts = ctx.Array("l", n_clients, lock=False)
                        url = f"ws://127.0.0.1:{settings.port}/api/live?token={token}"
                        proc = ctx.Process(
                            target=_live_clients_main, args=(url, n_clients, ready, stop, counts)
                        )
                        proc.start()
                        if not ready.wait(90):
                            proc.kill()
                            raise RuntimeError("the live clients did not connect")
                    _loop_samples(runtime)  # discard what came before this block
                    c0 = list(counts) if counts is not None else None
                    time.sleep(block_s)
                    got, tick = _loop_samples(runtime)
                    samples[n_clients] += got
                    ticks[n_clients] += tick
                    if proc is not None and stop is not None and counts is not None and c0 is not None:
                        live_rates += [(c1 - c) / block_s for c, c1 in zip(c0, list(counts), strict=True)]
                        stop.set()
                        proc.join(30)
                        if proc.is_alive():
                            proc.kill()
                    log(f"block {b + 1}/{blocks}, {n_clients:2d} live clients: {len(got)} decisions")
            log(f"REST: {rest_n} x GET {REST_ROUTE} at {REST_RATE_HZ:g}/s ...")
            out = ctx.Queue()
            rest = ctx.Process(target=_rest_client_main, args=(base, token, rest_n, REST_RATE_HZ, out))
            rest.start()
            rest_result = out.get(timeout=rest_n / REST_RATE_HZ + 120)
            rest.join(30)
            with contextlib.suppress(httpx.HTTPError):
                http.post(f"/api/trials/{trial_id}/stop")
    p95_0 = _pct(samples[0], 95)
    p95_n = _pct(samples[LIVE_CLIENTS], 95)
    tick_0 = _pct(ticks[0], 95)
    tick_n = _pct(ticks[LIVE_CLIENTS], 95)
    lat = rest_result["latencies_ms"]
    return {
        "benchmark": "api",
        "quick": quick,
        "frame_to_decision_ms": {
            "live_clients_0": _stats(samples[0]),
            "live_clients_20": _stats(samples[20]),
        },
        "live_clients_overhead": (p95_n / p95_0) if p95_0 and p95_n else None,
        "frame_tick_ms": {"live_clients_0": _stats(ticks[0]), "live_clients_20": _stats(ticks[20])},
        "frame_tick_overhead": (tick_n / tick_0) if tick_0 and tick_n else None,
        "live_msgs_per_s_per_client": {"median": _pct(live_rates, 50), "min": min(live_rates, default=None)},
        "rest": {
            "route": f"GET {REST_ROUTE}",
            "rate_hz": REST_RATE_HZ,
            "n": len(lat),
            "errors": rest_result["errors"],
            "p50_ms": _pct(lat, 50),
            "p95_ms": _pct(lat, 95),
            "max_ms": max(lat, default=None),
        },
        "snapshots_per_s": {
            "live_clients_0": len(ticks[0]) / (blocks * block_s),
            "live_clients_20": len(ticks[LIVE_CLIENTS]) / (blocks * block_s),
        },
        "blocks": blocks,
        "block_s": block_s,
        "cpu_count": os.cpu_count(),
        "loadavg_1min": {"start": load_start, "end": os.getloadavg()[0]},
    }
