"""``jepa-monitor bench``: ingestion throughput and latency against a real uvicorn server on loopback.

Each "decision" is what the robot loop sends per policy step: the decision record (z_hat) plus the realized
latent that scores an earlier decision, so the server does the full work (store, NMSE, episode scores).
Modes: one decision per request (JSON, then msgpack), batched msgpack over parallel connections, and the
MonitorClient's per-call cost in the control loop while its sender drains to the same server.
"""
from __future__ import annotations

import json
import os
import tempfile
import threading
import time
import uuid
from pathlib import Path

import httpx
import numpy as np

from monitor_service.client import MonitorClient
from monitor_service.encoding import MSGPACK_CONTENT_TYPE, pack
from monitor_service.server import start_server

HORIZON = 4
STEPS_PER_EPISODE = 200


def _records(rng: np.random.Generator, dim: int, start: int, count: int, prefix: str) -> list[list[dict]]:
    """Per decision: [decision, target-for-(step)] records of synthetic episodes of STEPS_PER_EPISODE steps."""
    out = []
    for i in range(start, start + count):
        ep, step = f"{prefix}-{i // STEPS_PER_EPISODE}", i % STEPS_PER_EPISODE
        z = rng.standard_normal(dim).astype("<f4")
        recs = [{"kind": "decision", "task": "bench", "episode": ep, "step": step, "horizon": HORIZON, "z_hat": z}]
        recs.append({"kind": "target", "episode": ep, "step": step + HORIZON, "z": z + 0.1})
        out.append(recs)
    return out


def _jsonable(recs: list[dict]) -> list[dict]:
    return [{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()} for r in recs]


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process (Linux /proc); None elsewhere."""
    try:
        fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _summary(name: str, n_decisions: int, seconds: float, latencies: list[float]) -> dict:
    lat = np.asarray(latencies) * 1000
    row = {
        "mode": name, "decisions": n_decisions, "seconds": round(seconds, 3),
        "decisions_per_s": round(n_decisions / seconds, 1), "requests": len(latencies),
        "p50_ms": round(float(np.percentile(lat, 50)), 3), "p99_ms": round(float(np.percentile(lat, 99)), 3),
    }
    print(f"{name:<28}{row['decisions_per_s']:>10.0f} decisions/s   p50 {row['p50_ms']:7.2f} ms   "
          f"p99 {row['p99_ms']:7.2f} ms   ({n_decisions} decisions, {len(latencies)} requests)", flush=True)
    return row


def _sequential(url: str, key: str, groups: list[list[dict]], binary: bool, max_seconds: float, name: str) -> dict:
    latencies = []
    with httpx.Client(base_url=url, timeout=30) as http:
        start = time.perf_counter()
        for recs in groups:
            if binary:
                kw = {"content": pack({"records": recs}), "headers": {"X-API-Key": key, "Content-Type": MSGPACK_CONTENT_TYPE}}
            else:
                kw = {"content": json.dumps({"records": _jsonable(recs)}), "headers": {"X-API-Key": key, "Content-Type": "application/json"}}
            t0 = time.perf_counter()
            r = http.post("/v1/batch", **kw)
            latencies.append(time.perf_counter() - t0)
            r.raise_for_status()
            if time.perf_counter() - start > max_seconds:
                break
        elapsed = time.perf_counter() - start
    return _summary(name, len(latencies), elapsed, latencies)


def _batched(url: str, key: str, groups: list[list[dict]], batch: int, concurrency: int, max_seconds: float) -> dict:
    bodies = [pack({"records": [r for g in groups[i : i + batch] for r in g]}) for i in range(0, len(groups), batch)]
    sizes = [len(groups[i : i + batch]) for i in range(0, len(groups), batch)]
    latencies: list[float] = []
    done = [0]
    lock = threading.Lock()
    next_i = [0]
    start = time.perf_counter()

    def worker():
        with httpx.Client(base_url=url, timeout=30) as http:
            while True:
                with lock:
                    i = next_i[0]
                    next_i[0] += 1
                if i >= len(bodies) or time.perf_counter() - start > max_seconds:
                    return
                t0 = time.perf_counter()
                r = http.post("/v1/batch", content=bodies[i], headers={
                    "X-API-Key": key, "Content-Type": MSGPACK_CONTENT_TYPE, "Idempotency-Key": uuid.uuid4().hex})
                dt = time.perf_counter() - t0
                r.raise_for_status()
                with lock:
                    latencies.append(dt)
                    done[0] += sizes[i]

    threads = [threading.Thread(target=worker) for _ in range(concurrency)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return _summary(f"binary batch={batch} x{concurrency}", done[0], time.perf_counter() - start, latencies)


def _client_cost(url: str, key: str, groups: list[list[dict]], max_seconds: float) -> dict:
    """Time MonitorClient.decision()/target() calls in a loop while its thread drains to the server."""
    per_call = []
    with MonitorClient(url, key, batch_size=256) as client:
        start = time.perf_counter()
        for recs in groups:
            d, t = recs
            t0 = time.perf_counter()
            client.decision(d["task"], d["episode"], d["step"], d["horizon"], d["z_hat"])
            client.target(t["episode"], t["step"], t["z"])
            per_call.append(time.perf_counter() - t0)
            if time.perf_counter() - start > max_seconds:
                break
        enqueue_s = time.perf_counter() - start
        client.flush(120)
        total = time.perf_counter() - start
    lat_us = np.asarray(per_call) * 1e6
    print(f"{'client per decision':<28}p50 {np.percentile(lat_us, 50):7.1f} us   p99 {np.percentile(lat_us, 99):7.1f} us   "
          f"(enqueue {len(per_call)} in {enqueue_s:.2f} s; all delivered after {total:.2f} s = "
          f"{len(per_call) / total:.0f} decisions/s end to end)", flush=True)
    return {"mode": "client", "decisions": len(per_call), "p50_us": float(np.percentile(lat_us, 50)),
            "p99_us": float(np.percentile(lat_us, 99)), "end_to_end_decisions_per_s": len(per_call) / total}


def run_bench(
    n: int = 4000, batches: tuple[int, ...] = (16, 64), dim: int = 256, max_seconds: float = 20.0, concurrency: int = 2
) -> list[dict]:
    """Start a fresh server on a temporary SQLite file, run every mode, print and return the numbers."""
    admin = "bench-admin-" + uuid.uuid4().hex
    with tempfile.TemporaryDirectory(prefix="jepa-monitor-bench-") as tmp:
        db_url = f"sqlite:///{Path(tmp) / 'bench.db'}"
        with start_server(db_url, admin_key=admin, log_path=Path(tmp) / "server.log") as server:
            http = httpx.Client(base_url=server.url, headers={"X-API-Key": admin}, timeout=30)
            http.put("/v1/tasks/bench", json={"latent_dim": dim}).raise_for_status()
            key = http.post("/v1/keys", json={"name": "bench-robot", "role": "robot", "robot": "bench-arm"}).json()["key"]
            http.close()
            rng = np.random.default_rng(0)
            print(f"jepa-monitor bench: latent dim {dim}, SQLite (WAL) at {db_url}, server {server.url}, 1 worker", flush=True)
            single_n = min(n, 1000)
            modes = [
                lambda: _sequential(server.url, key, _records(rng, dim, 0, single_n, "json"), False, max_seconds, "json, 1 decision/request"),
                lambda: _sequential(server.url, key, _records(rng, dim, 0, single_n, "bin"), True, max_seconds, "binary, 1 decision/request"),
                *[lambda b=b: _batched(server.url, key, _records(rng, dim, 0, n, f"batch{b}"), b, concurrency, max_seconds) for b in batches],
                lambda: _client_cost(server.url, key, _records(rng, dim, 0, n, "client"), max_seconds),
            ]
            rows = []
            for mode in modes:
                cpu0 = _cpu_seconds(server.process.pid)
                row = mode()
                cpu1 = _cpu_seconds(server.process.pid)
                if cpu0 is not None and cpu1 is not None:
                    # CPU the server spent per decision: unlike wall latency, not inflated by other load on the host.
                    row["server_cpu_ms_per_decision"] = round((cpu1 - cpu0) * 1000 / row["decisions"], 3)
                    print(f"{'':<28}server CPU {row['server_cpu_ms_per_decision']:.3f} ms per decision", flush=True)
                rows.append(row)
    return rows
