"""The append-only decision log (migration 0006): an existing database upgrades with its data and answers as before,
batches in flight when the server is killed (-9) are all there or not at all and every acknowledged one is there,
and publishing a batch's NMSEs at once counts exactly what one observation per value did."""
import concurrent.futures
import sqlite3
import threading
import time

import httpx
import numpy as np
import pytest
from alembic import command
from alembic.config import Config
from fastapi.testclient import TestClient
from monitor_testkit import ADMIN, DIM, make_settings, new_key
from prometheus_client import CollectorRegistry, Histogram

from monitor_service import db, scoring
from monitor_service.app import create_app
from monitor_service.metrics import NMSE_BUCKETS, observe_many
from monitor_service.server import free_port, start_server

OLD = "2026-01-02 03:04:05.000000"   # the instant one old request wrote its rows
LATER = "2026-01-02 03:04:06.500000"


def _latent(rng) -> bytes:
    return rng.normal(size=DIM).astype("<f4").tobytes()


def _at_0005(path):
    """A database at revision 0005 holding what the service stored before the decision log: a finished held-out
    episode (scored decisions, two requests), and a live one with z_now and named scores, two unscored decisions,
    a target no decision used yet and a decision that sent scores only."""
    engine = db.make_engine(f"sqlite:///{path}")
    db.upgrade(engine, "0005")
    engine.dispose()
    rng = np.random.default_rng(7)
    lat = {name: _latent(rng) for name in ("a0", "a1", "t1", "t2", "b0", "b0now", "b4", "tb4", "b8", "tb11")}
    with sqlite3.connect(path) as conn:
        conn.execute("INSERT INTO tasks (name, latent_dim, description, signals, created_at) VALUES "
                     "('Square', ?, '', '[\"stac\"]', ?)", (DIM, OLD))
        for eid, success, n, scored, ended in (("done", 1, 2, 2, OLD), ("live", None, 4, 1, None)):
            conn.execute(
                "INSERT INTO episodes (id, task, robot, held_out, success, n_decisions, n_scored, last_evaluated_step,"
                " over_count, under_count, alert_note, started_at, updated_at, ended_at, version, gaps, "
                "late_decisions, early_revisions, beyond_calibration) VALUES (?, 'Square', 'arm1', 1, ?, ?, ?, -1, 0,"
                " 0, '', ?, ?, ?, 3, 0, 0, 0, 0)", (eid, success, n, scored, OLD, OLD, ended))
        decisions = [  # episode, step, horizon, z_hat, nmse, z_now, persistence, scores, created_at
            ("done", 0, 1, lat["a0"], 0.25, None, None, None, OLD),
            ("done", 1, 1, lat["a1"], 0.5, None, None, None, LATER),
            ("live", 0, 4, lat["b0"], 0.125, lat["b0now"], 0.75, '{"stac": 0.5}', OLD),
            ("live", 2, None, None, None, None, None, '{"stac": 0.25}', OLD),
            ("live", 4, 4, lat["b4"], None, None, None, None, LATER),
            ("live", 8, 4, lat["b8"], None, None, None, None, LATER)]
        conn.executemany("INSERT INTO decisions (episode_id, step, horizon, target_step, z_hat, nmse, z_now, "
                         "nmse_persistence, scores, created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                         [(e, s, h, None if h is None else s + h, z, n, zn, p, sc, t)
                          for e, s, h, z, n, zn, p, sc, t in decisions])
        conn.executemany("INSERT INTO targets (episode_id, step, z, created_at) VALUES (?, ?, ?, ?)", [
            ("done", 1, lat["t1"], OLD), ("done", 2, lat["t2"], LATER), ("live", 4, lat["tb4"], OLD),
            ("live", 11, lat["tb11"], LATER)])
    return lat


def _tables(path) -> dict:
    with sqlite3.connect(path) as conn:
        return {"decisions": conn.execute(
                    "SELECT episode_id, step, horizon, target_step, z_hat, nmse, z_now, nmse_persistence, scores, "
                    "created_at FROM decisions ORDER BY episode_id, step").fetchall(),
                "targets": conn.execute("SELECT episode_id, step, z, created_at FROM targets "
                                        "ORDER BY episode_id, step").fetchall()}


def _alembic(engine, action, revision):
    cfg = Config()
    cfg.set_main_option("script_location", str(db.MIGRATIONS_DIR))
    with engine.begin() as conn:
        cfg.attributes["connection"] = conn
        getattr(command, action)(cfg, revision)


def test_a_0005_database_upgrades_with_its_data_and_the_service_goes_on_from_it(tmp_path):
    path = tmp_path / "monitor.db"
    lat = _at_0005(path)
    before = _tables(path)
    engine = db.make_engine(f"sqlite:///{path}")
    db.upgrade(engine)
    assert db.current_revision(engine) == "0006"
    with sqlite3.connect(path) as conn:
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        assert "decisions" not in tables and "targets" not in tables
        # one log row per episode and instant: the rows one old request wrote stay together with their time
        assert conn.execute("SELECT episode_id, created_at FROM decision_log ORDER BY id").fetchall() == [
            ("done", OLD), ("done", LATER), ("live", OLD), ("live", LATER)]
    # the downgrade gives the same rows back, and upgrading again is what it was
    _alembic(engine, "downgrade", "0005")
    assert _tables(path) == before
    db.upgrade(engine)
    engine.dispose()

    settings = make_settings(tmp_path)
    with TestClient(create_app(settings)) as client:
        op = new_key(client, "op", "operator")
        robot = new_key(client, "arm1", "robot", "arm1")
        done = client.get("/v1/episodes/done", headers=op).json()
        assert [(d["step"], d["nmse"], d["target_step"]) for d in done["decisions"]] == [(0, 0.25, 1), (1, 0.5, 2)]
        live = client.get("/v1/episodes/live", headers=op).json()
        assert live["decisions"] == [
            {"step": 0, "horizon": 4, "target_step": 4, "nmse": 0.125, "nmse_persistence": 0.75,
             "nmse_ratio": pytest.approx(0.125 / 0.75), "scores": {"stac": 0.5}},
            {"step": 2, "horizon": None, "target_step": None, "nmse": None, "nmse_persistence": None,
             "nmse_ratio": None, "scores": {"stac": 0.25}},
            {"step": 4, "horizon": 4, "target_step": 8, "nmse": None, "nmse_persistence": None, "nmse_ratio": None,
             "scores": None},
            {"step": 8, "horizon": 4, "target_step": 12, "nmse": None, "nmse_persistence": None, "nmse_ratio": None,
             "scores": None}]

        def z(name):
            return np.frombuffer(lat[name], dtype="<f4").tolist()

        def batch(records):
            return client.post("/v1/batch", json={"records": records}, headers=robot)

        # the migrated latents answer resends: the same decision and target again change nothing, others conflict
        same = {"kind": "decision", "task": "Square", "episode": "live", "step": 0, "horizon": 4, "z_hat": z("b0"),
                "z_now": z("b0now"), "scores": {"stac": 0.5}, "held_out": True}
        r = batch([same, {"kind": "target", "episode": "live", "step": 4, "z": z("tb4")}])
        assert r.status_code == 200 and r.json()["decisions"] == r.json()["targets"] == 0
        r = batch([{**same, "z_now": z("b0")}])
        assert r.status_code == 409 and "different decision at step 0" in r.json()["detail"]
        r = batch([{"kind": "target", "episode": "live", "step": 4, "z": z("b4")}])
        assert r.status_code == 409 and "different realized latent at step 4" in r.json()["detail"]
        # the migrated decision 4 is scored by the target sent now; new decisions find the stored targets: 4 (used
        # by decision 0, read back from the log) and 11 (unused, kept in memory)
        new_target = np.random.default_rng(8).normal(size=DIM).astype("<f4")
        r = batch([{"kind": "target", "episode": "live", "step": 8, "z": new_target.tolist()}])
        assert r.status_code == 200 and r.json()["scored"] == 1
        r = batch([{"kind": "decision", "task": "Square", "episode": "live", "step": 1, "horizon": 3,
                    "z_hat": z("b8"), "held_out": True},
                   {"kind": "decision", "task": "Square", "episode": "live", "step": 9, "horizon": 2,
                    "z_hat": z("b4"), "held_out": True}])
        assert r.status_code == 200 and r.json()["scored"] == 2
        live = client.get("/v1/episodes/live", headers=op).json()

        def nmse(a, b):
            return pytest.approx(scoring.nmse(np.frombuffer(a, "<f4"), np.frombuffer(b, "<f4")), rel=1e-12)

        assert [(d["step"], d["nmse"]) for d in live["decisions"]] == [
            (0, 0.125), (1, nmse(lat["b8"], lat["tb4"])), (2, None), (4, nmse(lat["b4"], new_target.tobytes())),
            (8, None), (9, nmse(lat["b4"], lat["tb11"]))]
        assert live["n_decisions"] == 6 and live["n_scored"] == 4
    engine = db.make_engine(settings.database_url)
    with engine.connect() as conn:
        assert [d["nmse"] is not None for d in db.read_decisions(conn, ["live"])["live"]] == [
            True, True, False, True, False, True]
    engine.dispose()


def test_kill_9_during_batches_keeps_every_acknowledged_one_whole(tmp_path):
    """Four writers send batches of 32 decisions with their targets (one episode each) while the server is killed
    (-9): every acknowledged batch is there after the restart, and every batch is there whole or not at all."""
    url = f"sqlite:///{tmp_path / 'monitor.db'}"
    port = free_port()
    server = start_server(url, admin_key=ADMIN, port=port, log_path=tmp_path / "s.log", ready_timeout=300)
    http = httpx.Client(base_url=server.url, timeout=120)
    try:
        http.put("/v1/tasks/Square", json={"latent_dim": DIM}, headers={"X-API-Key": ADMIN}).raise_for_status()
        robot = {"X-API-Key": http.post("/v1/keys", json={"name": "arm1", "role": "robot", "robot": "arm1"},
                                        headers={"X-API-Key": ADMIN}).json()["key"]}
        op = {"X-API-Key": http.post("/v1/keys", json={"name": "op", "role": "operator"},
                                     headers={"X-API-Key": ADMIN}).json()["key"]}
        acked: list[str] = []
        sent: list[str] = []
        lock = threading.Lock()
        stop = threading.Event()

        def writer(w: int) -> None:
            rng = np.random.default_rng(w)
            with httpx.Client(base_url=server.url, timeout=120) as h:
                for i in range(10_000):
                    if stop.is_set():
                        return
                    episode = f"w{w}-{i}"
                    records = []
                    for t in range(32):
                        z = rng.normal(size=DIM).astype(np.float32)
                        records += [{"kind": "decision", "task": "Square", "episode": episode, "step": t,
                                     "horizon": 1, "z_hat": (z * 1.1).tolist()},
                                    {"kind": "target", "episode": episode, "step": t + 1, "z": z.tolist()}]
                    with lock:
                        sent.append(episode)
                    try:
                        r = h.post("/v1/batch", json={"records": records}, headers=robot)
                    except httpx.TransportError:
                        return   # the server died with this batch in flight
                    assert r.status_code == 200, r.text
                    with lock:
                        acked.append(episode)

        with concurrent.futures.ThreadPoolExecutor(4) as pool:
            futures = [pool.submit(writer, w) for w in range(4)]
            deadline = time.monotonic() + 300   # a loaded machine may take minutes for the first few
            while len(acked) < 8 and time.monotonic() < deadline:
                time.sleep(0.05)
            server.kill()
            stop.set()
            for f in futures:
                f.result()
        assert len(acked) >= 8
        server = start_server(url, admin_key=ADMIN, port=port, log_path=tmp_path / "s.log", ready_timeout=300)
        found = {e["id"]: e for e in http.get("/v1/episodes?limit=5000", headers=op).json()}
        assert set(acked) <= set(found) <= set(sent)
        for episode in found:
            e = found[episode]
            assert e["n_decisions"] == e["n_scored"] == 32, e
            detail = http.get(f"/v1/episodes/{episode}", headers=op).json()
            assert [d["step"] for d in detail["decisions"]] == list(range(32))
            assert all(d["nmse"] == pytest.approx(0.01, rel=1e-4) for d in detail["decisions"])
        print(f"kill -9: {len(sent)} batches sent, {len(acked)} acknowledged, {len(found)} found after the restart")
        # the restarted server resumes an acknowledged episode from the log: a resend is recognised
        w, i = acked[-1].split("-")
        rng = np.random.default_rng(int(w[1:]))
        for _ in range(int(i) * 32):   # replay the writer's draws up to that batch
            rng.normal(size=DIM)
        z = rng.normal(size=DIM).astype(np.float32)
        r = http.post("/v1/batch", json={"records": [
            {"kind": "decision", "task": "Square", "episode": acked[-1], "step": 0, "horizon": 1,
             "z_hat": (z * 1.1).tolist()}]}, headers=robot)
        assert r.status_code == 200 and r.json()["decisions"] == 0, r.text
    finally:
        http.close()
        server.stop()


def test_observe_many_counts_what_one_observe_per_value_counts():
    values = [0.0, 0.01, 0.010000001, 0.3, 0.3, 1.0, 49.9, 50.0, 50.1, 1e9, -1.0, 0.75]
    registries = [CollectorRegistry(), CollectorRegistry()]
    one, many = (Histogram("h", "h", ["task"], buckets=NMSE_BUCKETS, registry=r) for r in registries)
    for v in values:
        one.labels("t").observe(v)
    observe_many(many.labels("t"), values[:5])
    observe_many(many.labels("t"), values[5:])
    def samples(registry):   # name, labels -> value; the sum to rounding (one addition per request, not per value)
        return {(m.name, s.name, tuple(sorted(s.labels.items()))): s.value for m in registry.collect()
                for s in m.samples if not s.name.endswith("_created")}

    got, want = samples(registries[1]), samples(registries[0])
    assert got == pytest.approx(want, rel=1e-15) and len(want) == len(NMSE_BUCKETS) + 3
