"""``jepa-monitor bench``: ingest throughput and latency against real servers on loopback, side by side with the
framework's floor (``floor.py``: bare FastAPI + SQLite inserting the same rows) in one run.

What a robot loop sends: a decision record (z_hat for step t + k) and, k steps later, the realized latent that
scores it. Modes, each with the same bodies against the service and against the floor:
- one record per request (decision or target alternately; JSON, then msgpack), from ``--concurrency``
  connections, as a fleet of robots would send them;
- batches of ``--batch`` decisions (each with its target) per msgpack request;
- the MonitorClient's own batching, end to end.
Service and floor alternate in ``--rounds`` rounds per mode, so that both meet the same load on a shared machine;
the ratios printed are the medians of the rounds' ratios.
The load comes from threads of this process on keep-alive connections; the server's CPU per request is read
from /proc (steadier than wall latency on a shared machine); the load average is printed with the numbers.
Every 2xx is committed and its alerts evaluated. With ``--servers 2`` on a PostgreSQL URL two server processes
share the database: the run checks afterwards that no record and no counter update was lost.
"""
from __future__ import annotations

import http.client
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
from tqdm import tqdm

from monitor_service.client import MonitorClient
from monitor_service.db import make_engine, read_decisions
from monitor_service.encoding import MSGPACK_CONTENT_TYPE, pack
from monitor_service.server import free_port, start_server

HORIZON = 4
STEPS_PER_EPISODE = 200
LATENTS = 64   # distinct latents cycled through, so bodies are built cheaply while every record is new


@dataclass
class Target:
    """A server to load: its base URL, the robot key to ingest with, and its PID when started here."""

    url: str
    key: str
    pid: int | None = None

    @property
    def host_port(self) -> tuple[str, int]:
        u = httpx.URL(self.url)
        return u.host, u.port


class Bodies:
    """Request bodies of one connection: its own episodes, decision t then the target t + HORIZON scoring it."""

    def __init__(self, dim: int, conn_id: str, binary: bool, batch: int, seed: int):
        rng = np.random.default_rng(seed)
        self.latents = [rng.standard_normal(dim).astype("<f4") for _ in range(LATENTS)]
        self.json_latents = [json.dumps(z.tolist()) for z in self.latents]
        self.binary, self.batch, self.conn_id, self.i = binary, batch, conn_id, 0

    def _record(self, kind: str, ep: str, step: int, j: int):
        if self.binary:
            if kind == "decision":
                return {"kind": "decision", "task": "bench", "episode": ep, "step": step, "horizon": HORIZON,
                        "z_hat": self.latents[j]}
            return {"kind": "target", "episode": ep, "step": step + HORIZON, "z": self.latents[(j + 1) % LATENTS]}
        if kind == "decision":
            return (f'{{"kind":"decision","task":"bench","episode":"{ep}","step":{step},"horizon":{HORIZON},'
                    f'"z_hat":{self.json_latents[j]}}}')
        z = self.json_latents[(j + 1) % LATENTS]
        return f'{{"kind":"target","episode":"{ep}","step":{step + HORIZON},"z":{z}}}'

    def next(self) -> tuple[str, bytes, int]:
        """(path, body, decisions in it): one record per request, or a batch of decisions and their targets."""
        if self.batch == 0:
            n, kind = divmod(self.i, 2)
            self.i += 1
            ep, step = f"{self.conn_id}-{n // STEPS_PER_EPISODE}", n % STEPS_PER_EPISODE
            rec = self._record("decision" if kind == 0 else "target", ep, step, n % LATENTS)
            path = "/v1/decisions" if kind == 0 else "/v1/targets"
            return path, (pack(rec) if self.binary else rec.encode()), 1 - kind
        recs = []
        for _ in range(self.batch):
            n = self.i
            self.i += 1
            ep, step = f"{self.conn_id}-{n // STEPS_PER_EPISODE}", n % STEPS_PER_EPISODE
            recs += [self._record("decision", ep, step, n % LATENTS), self._record("target", ep, step, n % LATENTS)]
        body = pack({"records": recs}) if self.binary else ('{"records":[' + ",".join(recs) + "]}").encode()
        return "/v1/batch", body, self.batch


def _cpu_seconds(pid: int | None) -> float | None:
    """User + system CPU time of a process and its children (Linux /proc); None elsewhere."""
    if pid is None:
        return None
    total = 0.0
    pids = [pid] + [int(p) for p in _child_pids(pid)]
    for p in pids:
        try:
            fields = open(f"/proc/{p}/stat").read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def _child_pids(pid: int) -> list[str]:
    try:
        return open(f"/proc/{pid}/task/{pid}/children").read().split()
    except OSError:
        return []


def load(targets: list[Target], binary: bool, batch: int, dim: int, concurrency: int, seconds: float, tag: str) -> dict:
    """Closed-loop load from ``concurrency`` keep-alive connections spread over ``targets`` for ``seconds``."""
    latencies: list[float] = []
    counts = {"requests": 0, "decisions": 0, "records": 0}
    errors: list[str] = []
    lock = threading.Lock()
    deadline = time.perf_counter() + seconds
    content_type = MSGPACK_CONTENT_TYPE if binary else "application/json"

    def connection(c: int) -> None:
        target = targets[c % len(targets)]
        bodies = Bodies(dim, f"{tag}-{uuid.uuid4().hex[:8]}-c{c}", binary, batch, seed=c)
        host, port = target.host_port
        conn = http.client.HTTPConnection(host, port, timeout=60)
        mine, n_req, n_dec, n_rec = [], 0, 0, 0
        headers = {"X-API-Key": target.key, "Content-Type": content_type}
        try:
            while time.perf_counter() < deadline:
                path, body, decisions = bodies.next()
                t0 = time.perf_counter()
                conn.request("POST", path, body, headers)
                resp = conn.getresponse()
                data = resp.read()
                mine.append(time.perf_counter() - t0)
                if resp.status != 200:
                    with lock:
                        errors.append(f"{resp.status} {data[:200]!r}")
                    return
                n_req += 1
                n_dec += decisions
                n_rec += 1 if batch == 0 else 2 * batch
        finally:
            conn.close()
            with lock:
                latencies.extend(mine)
                counts["requests"] += n_req
                counts["decisions"] += n_dec
                counts["records"] += n_rec

    cpu0 = [_cpu_seconds(t.pid) for t in targets]
    start = time.perf_counter()
    threads = [threading.Thread(target=connection, args=(c,)) for c in range(concurrency)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    elapsed = time.perf_counter() - start
    cpu1 = [_cpu_seconds(t.pid) for t in targets]
    if errors:
        raise RuntimeError(f"the server refused a request: {errors[0]}")
    if not latencies:
        raise RuntimeError(f"no request was answered in {seconds:g} s (load average {os.getloadavg()[0]:.1f}); "
                           "run the bench with more --seconds, fewer --rounds or on a quieter machine")
    cpu = sum(cpu1) - sum(cpu0) if all(c is not None for c in cpu0 + cpu1) else None
    return _row(counts, elapsed, latencies, cpu)


def _row(counts: dict, elapsed: float, latencies: list[float], cpu_s: float | None) -> dict:
    lat = np.asarray(latencies) * 1000
    row = {"requests_per_s": counts["requests"] / elapsed, "decisions_per_s": counts["decisions"] / elapsed,
           "records_per_s": counts["records"] / elapsed, "p50_ms": float(np.percentile(lat, 50)),
           "p99_ms": float(np.percentile(lat, 99)), **counts, "seconds": elapsed}
    if cpu_s is not None:
        row["server_cpu_ms_per_request"] = cpu_s * 1000 / max(1, counts["requests"])
    row["_latencies"], row["_cpu_s"] = latencies, cpu_s
    return row


def _merged(rows: list[dict]) -> dict:
    """One row from several rounds of the same mode: totals over all of them."""
    counts = {k: sum(r[k] for r in rows) for k in ("requests", "decisions", "records")}
    cpu = None if any(r["_cpu_s"] is None for r in rows) else sum(r["_cpu_s"] for r in rows)
    row = _row(counts, sum(r["seconds"] for r in rows), [x for r in rows for x in r["_latencies"]], cpu)
    return _public(row)


def _public(row: dict) -> dict:
    return {k: v for k, v in row.items() if not k.startswith("_")}


def side_by_side(targets: list[Target], floor_target: Target | None, binary: bool, batch: int, dim: int,
                 concurrency: int, seconds: float, rounds: int) -> dict:
    """The service and the floor in alternating rounds of ``seconds / rounds`` each, so that both see the same
    load on a shared machine; per-round ratios (floor's CPU per request / the service's, the service's requests
    per second / the floor's) and their medians beside the totals."""
    ours, theirs = [], []
    rounds = rounds if floor_target is not None else 1
    for _ in range(rounds):
        ours.append(load(targets, binary, batch, dim, concurrency, seconds / rounds, "svc"))
        if floor_target is not None:
            theirs.append(load([floor_target], binary, batch, dim, concurrency, seconds / rounds, "floor"))
    out = {"service": _merged(ours), "floor": _merged(theirs) if theirs else None, "rounds": rounds}
    if theirs:
        out["throughput_ratio_per_round"] = [o["requests_per_s"] / t["requests_per_s"] for o, t in zip(ours, theirs)]
        out["throughput_ratio_median"] = float(np.median(out["throughput_ratio_per_round"]))
        if all("server_cpu_ms_per_request" in r for r in ours + theirs):
            # /proc counts CPU in clock ticks (10 ms): a short round can read 0 on either side; no ratio then
            per_round = [t["server_cpu_ms_per_request"] / o["server_cpu_ms_per_request"]
                         if o["server_cpu_ms_per_request"] > 0 and t["server_cpu_ms_per_request"] > 0 else None
                         for o, t in zip(ours, theirs)]
            out["cpu_ratio_per_round"] = per_round
            measured = [r for r in per_round if r is not None]
            if measured:
                out["cpu_ratio_median"] = float(np.median(measured))
    return out


def client_end_to_end(target: Target, dim: int, decisions: int, seconds: float) -> dict:
    """MonitorClient: per-call cost in the control loop, and decisions/s until all are delivered."""
    rng = np.random.default_rng(1)
    latents = [rng.standard_normal(dim).astype("<f4") for _ in range(LATENTS)]
    per_call, run = [], uuid.uuid4().hex[:8]
    with MonitorClient(target.url, target.key, batch_size=256) as client:
        start = time.perf_counter()
        for i in range(decisions):
            ep, step = f"client-{run}-{i // STEPS_PER_EPISODE}", i % STEPS_PER_EPISODE
            t0 = time.perf_counter()
            client.decision("bench", ep, step, HORIZON, latents[i % LATENTS])
            client.target(ep, step + HORIZON, latents[(i + 1) % LATENTS])
            per_call.append(time.perf_counter() - t0)
            if time.perf_counter() - start > seconds:
                break
        client.flush(300)
        total = time.perf_counter() - start
    us = np.asarray(per_call) * 1e6
    return {"decisions": len(per_call), "decisions_per_s": len(per_call) / total,
            "call_p50_us": float(np.percentile(us, 50)), "call_p99_us": float(np.percentile(us, 99))}


def _provision(url: str, admin_key: str, dim: int) -> str:
    with httpx.Client(base_url=url, headers={"X-API-Key": admin_key}, timeout=30) as http:
        r = http.put("/v1/tasks/bench", json={"latent_dim": dim})
        if r.status_code != 200:
            raise RuntimeError(f"registering the bench task failed: {r.status_code} {r.text}")
        r = http.post("/v1/keys", json={"name": f"bench-robot-{uuid.uuid4().hex[:8]}", "role": "robot",
                                        "robot": "bench-arm"})
        r.raise_for_status()
        return r.json()["key"]


def start_floor(tmp: Path) -> tuple[subprocess.Popen, Target]:
    """The floor app (floor.py) under uvicorn, one worker, on a free loopback port."""
    port = free_port()
    env = dict(os.environ, JEPA_MONITOR_FLOOR_DB=str(tmp / "floor.db"))
    proc = subprocess.Popen([sys.executable, "-m", "uvicorn", "monitor_service.floor:create_app", "--factory",
                             "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            httpx.get(url + "/docs", timeout=1)
            return proc, Target(url, "", proc.pid)
        except httpx.TransportError:
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("the floor server did not start")


def _verify_no_lost_updates(database_url: str) -> dict:
    """Every decision row counted on its episode, every scored decision counted as scored (PostgreSQL runs)."""
    from sqlalchemy import text

    engine = make_engine(database_url)
    with engine.connect() as conn:
        counters = conn.execute(text("SELECT id, n_decisions, n_scored FROM episodes WHERE task = 'bench'")).all()
        decisions = read_decisions(conn, [r[0] for r in counters])
    engine.dispose()
    rows = [(eid, n, scored, len(decisions[eid]), sum(d["nmse"] is not None for d in decisions[eid]))
            for eid, n, scored in counters]
    bad = [r for r in rows if r[1] != r[3] or r[2] != r[4]]
    return {"episodes": len(rows), "decisions": sum(r[3] for r in rows), "mismatched_episodes": len(bad)}


def _line(mode: str, measured: dict) -> str:
    ours, floor = measured["service"], measured["floor"]
    cpu = ours.get("server_cpu_ms_per_request")
    text = (f"{mode:<34}{ours['requests_per_s']:>8.0f} req/s {ours['decisions_per_s']:>8.0f} dec/s "
            f"p50 {ours['p50_ms']:6.2f} p99 {ours['p99_ms']:6.2f} ms" + (f"  CPU {cpu:.2f} ms/req" if cpu else ""))
    if floor is not None:
        floor_cpu = floor.get("server_cpu_ms_per_request")
        text += (f" | floor {floor['requests_per_s']:>7.0f} req/s p99 {floor['p99_ms']:6.2f} ms"
                 + (f" CPU {floor_cpu:.2f} ms/req" if floor_cpu else "")
                 + f" | ratio {measured['throughput_ratio_median']:.2f}")
        if "cpu_ratio_median" in measured:
            text += f", CPU ratio {measured['cpu_ratio_median']:.2f}"
        if measured["rounds"] > 1:
            text += f" (medians of {measured['rounds']} alternating rounds)"
    return text


def run_bench(dim: int = 1024, seconds: float = 8.0, concurrency: int = 8, batch: int = 64, batch_concurrency: int = 2,
              host: str | None = None, port: int | None = None, admin_key: str | None = None,
              database_url: str | None = None, servers: int = 1, workers: int = 1, client_decisions: int = 20_000,
              floor: bool = True, rounds: int = 4, progress: bool = False, out=None) -> dict:
    """Run every mode against the service (started here, or at ``host:port``) and the floor, in ``rounds``
    alternating rounds that together last ``seconds``; print each row to ``out`` (default stdout) as it is measured
    (``progress``: a bar of the modes on stderr) and return every number."""
    if rounds < 1:
        raise ValueError(f"rounds must be at least 1, got {rounds}")
    results: dict = {"dim": dim, "load_average_before": os.getloadavg(), "modes": {}}

    def echo(text: str) -> None:
        tqdm.write(text, file=out or sys.stdout)   # above the bar, when there is one

    with tempfile.TemporaryDirectory(prefix="jepa-monitor-bench-") as tmp, ExitStack() as stack:
        tmp = Path(tmp)
        if host or port:
            if not admin_key:
                raise ValueError("--host/--port need --admin-key: the bench registers its task and a robot key")
            url = f"http://{host or '127.0.0.1'}:{port or 8765}"
            targets = [Target(url, _provision(url, admin_key, dim))]
            where = f"the server at {url}"
        else:
            admin_key = "bench-admin-" + uuid.uuid4().hex
            database_url = database_url or f"sqlite:///{tmp / 'bench.db'}"
            targets = []
            for i in range(servers):
                server = stack.enter_context(start_server(
                    database_url, admin_key=admin_key, workers=workers, log_path=tmp / f"server{i}.log",
                    env={"PROMETHEUS_MULTIPROC_DIR": str(tmp / f"prom{i}")} if workers > 1 else None))
                targets.append(Target(server.url, "", server.process.pid))
            key = _provision(targets[0].url, admin_key, dim)
            for t in targets:
                t.key = key
            backend = database_url.split(":", 1)[0]
            where = f"{servers} server process(es) x {workers} worker(s) on {backend}"
        floor_target = None
        if floor:
            proc, floor_target = start_floor(tmp)
            stack.callback(proc.kill)
        echo(f"jepa-monitor bench: latent dim {dim}, {where}; {seconds:g} s per mode; load average "
              f"{results['load_average_before'][0]:.2f} before the run (2xx = committed, alerts evaluated)")
        modes = [(f"json, 1 record/request x{concurrency}", False, 0, concurrency),
                 (f"msgpack, 1 record/request x{concurrency}", True, 0, concurrency),
                 (f"msgpack, {batch} decisions/request x{batch_concurrency}", True, batch, batch_concurrency)]
        bar = stack.enter_context(tqdm(total=len(modes) + bool(client_decisions), desc="jepa-monitor bench",
                                       unit="mode", disable=not progress, file=sys.stderr))
        for name, binary, size, conns in modes:
            measured = side_by_side(targets, floor_target, binary, size, dim, conns, seconds, rounds)
            results["modes"][name] = measured
            echo(_line(name, measured))
            bar.update()
        if client_decisions:
            row = client_end_to_end(targets[0], dim, client_decisions, seconds)
            bar.update()
            results["modes"]["MonitorClient end to end"] = row
            echo(f"{'MonitorClient end to end':<34}{row['decisions_per_s']:>23.0f} dec/s   call p50 "
                  f"{row['call_p50_us']:.1f} us p99 {row['call_p99_us']:.1f} us per decision")
        if database_url and database_url.startswith("postgresql") and not (host or port):
            check = _verify_no_lost_updates(database_url)
            results["postgres_check"] = check
            echo(f"PostgreSQL, {servers} servers: {check['decisions']} decisions on {check['episodes']} episodes; "
                  f"episodes whose counters disagree with their rows: {check['mismatched_episodes']}")
        results["load_average_after"] = os.getloadavg()
        echo(f"load average after the run: {results['load_average_after'][0]:.2f}")
    return results
