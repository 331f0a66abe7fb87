"""Against a real uvicorn server in a subprocess: kill -9 restart, link outage, concurrent writers, workers."""
import asyncio
import json
import os
import signal
import time
import concurrent.futures
import re
from pathlib import Path

import httpx
import numpy as np
import pytest
from monitor_testkit import ADMIN, DIM, alive, children, episode_records

from monitor_service.client import AsyncMonitorClient, MonitorClient
from monitor_service.server import free_port, provision, start_server

A = {"X-API-Key": ADMIN}


def _setup(url):
    http = httpx.Client(base_url=url, timeout=30)
    assert http.put("/v1/tasks/Square", json={"latent_dim": DIM}, headers=A).status_code == 200
    robot = {"X-API-Key": http.post("/v1/keys", json={"name": "arm1", "role": "robot", "robot": "arm1"},
                                    headers=A).json()["key"]}
    op = {"X-API-Key": http.post("/v1/keys", json={"name": "op", "role": "operator"}, headers=A).json()["key"]}
    return http, robot, op


@pytest.fixture
def db_url(tmp_path):
    return f"sqlite:///{tmp_path / 'monitor.db'}"


def test_kill_9_loses_nothing_acknowledged(db_url, tmp_path):
    port = free_port()
    server = start_server(db_url, admin_key=ADMIN, port=port, log_path=tmp_path / "s.log")
    try:
        http, robot, op = _setup(server.url)
        rng = np.random.default_rng(0)
        acked = []
        for i in range(20):
            recs, _ = episode_records(f"e{i}", "Square", rng, 0.4, n_steps=6, success=i % 2 == 0)
            r = http.post("/v1/batch", json={"records": recs}, headers={**robot, "Idempotency-Key": f"b{i}"})
            assert r.status_code == 200
            acked.append(f"e{i}")
        server.kill()  # SIGKILL right after the last 2xx
        server = start_server(db_url, admin_key=ADMIN, port=port, log_path=tmp_path / "s.log")
        eps = {e["id"]: e for e in http.get("/v1/episodes?limit=1000", headers=op).json()}
        assert set(eps) == set(acked)
        assert all(e["n_decisions"] == 6 and e["n_scored"] == 6 and e["early_score"] is not None for e in eps.values())
        assert [eps[f"e{i}"]["success"] for i in range(20)] == [i % 2 == 0 for i in range(20)]
        # A retry after the restart is still recognised by its persisted Idempotency-Key.
        recs, _ = episode_records("e19", "Square", np.random.default_rng(99), 0.4, n_steps=6)
        r = http.post("/v1/batch", json={"records": recs}, headers={**robot, "Idempotency-Key": "b19"})
        assert r.status_code == 409  # same key, different body
        http.close()
    finally:
        server.stop()


def test_client_survives_outage_and_delivers_in_order(db_url, tmp_path):
    port = free_port()
    server = start_server(db_url, admin_key=ADMIN, port=port, log_path=tmp_path / "s.log")
    try:
        http, robot, op = _setup(server.url)
        rng = np.random.default_rng(1)
        client = MonitorClient(server.url, robot["X-API-Key"], batch_size=8, max_backoff=0.2)
        try:
            z = rng.normal(size=(40, DIM))
            for t in range(20):
                assert client.decision("Square", "out", t, 1, z[t] * 1.1)
                assert client.target("out", t + 1, z[t])
            assert client.flush(30)
            server.kill()
            for t in range(20, 40):  # the link is down: calls return at once and records wait in the buffer
                assert client.decision("Square", "out", t, 1, z[t] * 1.1)
                assert client.target("out", t + 1, z[t])
            assert client.outcome("out", False)
            assert client.pending > 0
            server = start_server(db_url, admin_key=ADMIN, port=port, log_path=tmp_path / "s.log")
            assert client.flush(60), f"{client.pending} records still buffered"
        finally:
            client.close()
        assert client.stats.rejected == [] and client.stats.dropped == 0 and client.stats.sent == 81
        ep = http.get("/v1/episodes/out", headers=op).json()
        assert [d["step"] for d in ep["decisions"]] == list(range(40))
        assert ep["n_scored"] == 40 and ep["success"] is False
        assert all(d["nmse"] == pytest.approx(0.01, rel=1e-4) for d in ep["decisions"])
        http.close()
    finally:
        server.stop()


def test_client_buffer_is_bounded_and_rejections_are_reported(db_url, tmp_path):
    with start_server(db_url, admin_key=ADMIN, log_path=tmp_path / "s.log") as server:
        http, robot, _ = _setup(server.url)
        with MonitorClient(server.url, robot["X-API-Key"], batch_size=4) as client:
            assert client.decision("Square", "b", 0, 1, np.ones(DIM))
            assert client.target("ghost", 1, np.ones(DIM))  # unknown episode: refused by the server
            assert client.decision("Square", "b", 1, 1, np.ones(DIM))
            assert client.flush(30)
            with pytest.raises(ValueError, match="NaN"):
                client.decision("Square", "b", 2, 1, np.full(DIM, np.nan))
        assert client.stats.sent == 3 and len(client.stats.rejected) == 1
        assert client.stats.rejected[0][1] == 404 and "ghost" in client.stats.rejected[0][2]
        dead = MonitorClient(f"http://127.0.0.1:{free_port()}", "k", max_buffer=3, max_backoff=0.05)
        results = [dead.decision("Square", "x", t, 1, np.ones(DIM)) for t in range(5)]
        assert results == [True, True, True, False, False] and dead.stats.dropped == 2
        assert dead.close(timeout=0.2) is False
        http.close()


def test_async_client(db_url, tmp_path):
    with start_server(db_url, admin_key=ADMIN, log_path=tmp_path / "s.log") as server:
        robot = {"X-API-Key": provision(server.url, ADMIN, {"Square": DIM}, robot="arm1")}
        http = httpx.Client(base_url=server.url, timeout=30)
        op = A
        with pytest.raises(RuntimeError, match="already uses latent_dim 16"):
            provision(server.url, ADMIN, {"Square": DIM + 1}, robot="arm2")

        async def loop():
            async with AsyncMonitorClient(server.url, robot["X-API-Key"], batch_size=5) as client:
                for t in range(12):
                    client.decision("Square", "async", t, 2, np.full(DIM, 1.0 + t))
                    await asyncio.sleep(0)
                for t in range(2, 14):
                    client.target("async", t, np.full(DIM, float(t - 1)))
                client.outcome("async", True)
                assert await client.flush(30)
            return client.stats

        stats = asyncio.run(loop())
        assert stats.sent == 25 and stats.rejected == []
        ep = http.get("/v1/episodes/async", headers=op).json()
        assert ep["n_scored"] == 12 and ep["success"] is True
        # z_hat = 1 + t vs z = t + 1: exact prediction, NMSE 0
        assert [d["nmse"] for d in ep["decisions"]] == [0.0] * 12
        http.close()


def test_concurrent_writers_two_workers_and_metrics_aggregate(db_url, tmp_path):
    with start_server(db_url, admin_key=ADMIN, workers=2, log_path=tmp_path / "s.log",
                      env={"PROMETHEUS_MULTIPROC_DIR": str(tmp_path / "prom")}) as server:
        http, robot, op = _setup(server.url)

        def writer(w):
            rng = np.random.default_rng(w)
            with httpx.Client(base_url=server.url, timeout=60) as h:
                for i in range(6):
                    recs, _ = episode_records(f"w{w}-e{i}", "Square", rng, 0.4, n_steps=5)
                    key = {"Idempotency-Key": f"w{w}-{i}"}
                    r = h.post("/v1/batch", json={"records": recs}, headers={**robot, **key})
                    assert r.status_code == 200, r.text
                    # An immediate retry of the same request (e.g. after a timeout) changes nothing.
                    r2 = h.post("/v1/batch", json={"records": recs}, headers={**robot, **key})
                    assert r2.status_code == 200 and r2.headers.get("Idempotent-Replayed") == "true"
                    # And the same episode written twice concurrently by two writers is not double counted.
                    shared, _ = episode_records("shared", "Square", np.random.default_rng(1000 + i), 0.4, n_steps=1)
                    shared[0]["step"] = i
                    shared[1]["step"] = i + 1
                    h.post("/v1/batch", json={"records": shared[:1]}, headers=robot)

        with concurrent.futures.ThreadPoolExecutor(4) as pool:
            list(pool.map(writer, range(4)))
        eps = http.get("/v1/episodes?limit=1000", headers=op).json()
        assert len(eps) == 25
        assert all(e["n_decisions"] == 5 and e["n_scored"] == 5 for e in eps if e["id"] != "shared")
        assert next(e for e in eps if e["id"] == "shared")["n_decisions"] == 6
        # Scrape several times: whichever worker answers, counters cover both workers' requests.
        for _ in range(4):
            text = http.get("/metrics", headers=op).text
            total = float(re.search(r'jepa_monitor_decisions_total\{robot="arm1",task="Square"\} ([0-9.e+]+)',
                                    text).group(1))
            assert total == 4 * 6 * 5 + 6
        http.close()


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads the process tree from /proc")
def test_workers_exit_when_the_supervisor_is_killed(db_url, tmp_path):
    """kill -9 of the supervising PID only: its workers must go, so a restart finds the port free."""
    server = start_server(db_url, admin_key=ADMIN, workers=2, log_path=tmp_path / "s.log",
                          env={"PROMETHEUS_MULTIPROC_DIR": str(tmp_path / "prom")})
    try:
        workers = [c for c in children(server.process.pid)
                   if "spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes().decode(errors="replace")]
        assert len(workers) == 2, workers
        os.kill(server.process.pid, signal.SIGKILL)     # the supervisor alone, not its process group
        server.process.wait(10)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and any(alive(w) for w in workers):
            time.sleep(0.2)
        survivors = [w for w in workers if alive(w)]
        assert survivors == [], f"workers {survivors} outlived their supervisor"
        with pytest.raises(httpx.TransportError):
            httpx.get(server.url + "/healthz", timeout=2)
        restarted = start_server(db_url, admin_key=ADMIN, port=server.port, log_path=tmp_path / "s2.log")
        restarted.stop()
    finally:
        server.kill()


def test_bench_compares_the_service_with_the_floor_in_one_run(capsys):
    from monitor_service.bench import run_bench

    out = run_bench(dim=16, seconds=0.7, concurrency=2, batch=8, batch_concurrency=1, client_decisions=40)
    modes = out["modes"]
    assert list(modes) == ["json, 1 record/request x2", "msgpack, 1 record/request x2",
                           "msgpack, 8 decisions/request x1", "MonitorClient end to end"]
    for name in list(modes)[:3]:
        ours, floor = modes[name]["service"], modes[name]["floor"]
        assert ours["requests"] > 0 and floor["requests"] > 0 and ours["p99_ms"] >= ours["p50_ms"] > 0
        assert ours["server_cpu_ms_per_request"] > 0
        # service and floor alternate: a ratio per round, the printed one their median
        assert modes[name]["rounds"] == 4 and len(modes[name]["cpu_ratio_per_round"]) == 4
        assert modes[name]["throughput_ratio_median"] == float(np.median(modes[name]["throughput_ratio_per_round"]))
        assert not any(k.startswith("_") for k in ours)   # the rounds' raw latencies are not kept in the JSON
    assert modes["msgpack, 8 decisions/request x1"]["service"]["decisions"] == \
        8 * modes["msgpack, 8 decisions/request x1"]["service"]["requests"]
    assert modes["MonitorClient end to end"]["decisions"] == 40
    text = capsys.readouterr().out
    assert "| floor" in text and "| ratio" in text and "load average" in text


def test_bench_rounds_whose_cpu_reads_zero_ticks_give_no_cpu_ratio(monkeypatch):
    """/proc counts CPU in clock ticks: a short round may read 0 on one side. That round has no CPU ratio; the
    median is over the others (no division by zero)."""
    from monitor_service import bench

    cpu = iter([0.0, 5.0, 4.0, 2.0, 5.0, 0.0])   # service, floor, service, floor, ...
    def fake_load(targets, binary, batch, dim, concurrency, seconds, tag):
        return bench._row({"requests": 10, "decisions": 10, "records": 10}, 1.0, [0.001] * 10,
                          next(cpu) * 10 / 1000)
    monkeypatch.setattr(bench, "load", fake_load)
    out = bench.side_by_side([bench.Target("http://x", "k")], bench.Target("http://y", ""), True, 0, 8, 1, 3.0, 3)
    assert out["cpu_ratio_per_round"] == [None, 0.5, None] and out["cpu_ratio_median"] == 0.5
    assert out["throughput_ratio_per_round"] == [1.0, 1.0, 1.0]


def test_bench_command_prints_json_with_json_and_writes_it_with_out(tmp_path, capsys):
    from monitor_service.cli import main

    saved = tmp_path / "bench.json"
    assert main(["bench", "--dim", "8", "--seconds", "0.3", "--concurrency", "1", "--batch", "4",
                 "--batch-concurrency", "1", "--client-decisions", "0", "--no-floor", "--json", "--out",
                 str(saved)]) == 0
    out, err = capsys.readouterr()
    printed = json.loads(out)                       # stdout is the JSON alone; the rows went to stderr
    assert list(printed["modes"]) == ["json, 1 record/request x1", "msgpack, 1 record/request x1",
                                      "msgpack, 4 decisions/request x1"]
    assert json.loads(saved.read_text())["modes"].keys() == printed["modes"].keys()
    assert "jepa-monitor bench: latent dim 8" in err and "jepa-monitor bench:" not in out
    assert main(["bench", "--dim", "8", "--seconds", "0.3", "--concurrency", "1", "--batch", "4",
                 "--batch-concurrency", "1", "--client-decisions", "0", "--no-floor"]) == 0
    out, err = capsys.readouterr()
    assert "jepa-monitor bench: latent dim 8" in out and "jepa-monitor bench" in err   # the rows, and the bar


def test_bench_runs_against_a_server_someone_else_started(db_url, tmp_path, capsys):
    from monitor_service.bench import run_bench

    with start_server(db_url, admin_key=ADMIN, log_path=tmp_path / "s.log") as server:
        out = run_bench(dim=8, seconds=0.5, concurrency=1, batch=4, batch_concurrency=1, client_decisions=0,
                        host="127.0.0.1", port=server.port, admin_key=ADMIN, floor=False)
        assert all(m["service"]["requests"] > 0 and m["floor"] is None for m in out["modes"].values())
        assert f"the server at {server.url}" in capsys.readouterr().out
        with pytest.raises(ValueError, match="--admin-key"):
            run_bench(host="127.0.0.1", port=server.port)


def test_ingest_never_blocks_the_event_loop_on_the_write_lock(client, robot):
    """The write lock may be held by a request of another route until its session's teardown, which the event
    loop runs: an ingest request that waited for it on the loop never returned (a live deadlock seen after PUT
    /v1/tasks). Now it waits in a worker thread while the loop keeps answering."""
    import threading
    import time

    from monitor_testkit import episode_records, post_batch, register_task

    register_task(client, "Square")
    recs, _ = episode_records("locked", "Square", np.random.default_rng(0), 0.3, n_steps=2)
    lock = client.app.state.write_lock
    lock.acquire()
    answer = {}
    sender = threading.Thread(target=lambda: answer.setdefault("r", post_batch(client, robot, recs)))
    sender.start()
    time.sleep(0.3)
    start = time.monotonic()
    assert client.get("/healthz").status_code == 200
    assert time.monotonic() - start < 2.0, "the event loop waited for the write lock"
    assert "r" not in answer   # the ingest waits for the lock, off the loop
    lock.release()
    sender.join(10)
    assert answer["r"].status_code == 200 and answer["r"].json()["decisions"] == 2
