"""The same service on a real PostgreSQL (Debian's postgresql binaries in a temp dir), when they exist."""
import concurrent.futures
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from monitor_testkit import ADMIN, DIM, alive, children, episode_records

from monitor_service import db
from monitor_service.server import free_port, start_server

PG_BIN = "/usr/lib/postgresql/15/bin"
pytestmark = pytest.mark.skipif(
    not os.path.exists(f"{PG_BIN}/initdb"),
    reason="PostgreSQL server binaries are not installed (apt-get install postgresql)"
)


@pytest.fixture(scope="module")
def pg_url():
    pytest.importorskip("psycopg", reason="psycopg 3 is not installed (it comes with the monitor extra)")
    # Directly under /tmp: pytest's own temp root is private to root, which the postgres user cannot enter.
    root = Path(tempfile.mkdtemp(prefix="jepa-monitor-pg-"))
    # PostgreSQL refuses to run as root: run it as the postgres system user then.
    prefix = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []
    if prefix:
        shutil.chown(root, "postgres")
    port = free_port()
    data, log = root / "data", root / "log"
    subprocess.run(prefix + [f"{PG_BIN}/initdb", "-D", str(data), "-A", "trust", "-U", "postgres"], check=True,
                   capture_output=True)
    opts = f"-p {port} -k {root} -c listen_addresses=127.0.0.1 -c fsync=off"
    subprocess.run(prefix + [f"{PG_BIN}/pg_ctl", "-D", str(data), "-o", opts, "-l", str(log), "-w", "start"],
                   check=True, capture_output=True)
    try:
        yield f"postgresql+psycopg://postgres@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run(prefix + [f"{PG_BIN}/pg_ctl", "-D", str(data), "-m", "immediate", "-w", "stop"],
                       capture_output=True)
        shutil.rmtree(root, ignore_errors=True)


def test_migrations_on_postgres(pg_url):
    engine = db.make_engine(pg_url)
    db.upgrade(engine)
    db.upgrade(engine)
    assert db.current_revision(engine) == db.head_revision()
    with engine.connect() as conn:
        assert compare_metadata(MigrationContext.configure(conn), db.Base.metadata) == []
    engine.dispose()


def test_service_on_postgres_concurrent_idempotent_calibrated_and_restarted(pg_url, tmp_path):
    A = {"X-API-Key": ADMIN}
    port = free_port()
    server = start_server(pg_url, admin_key=ADMIN, port=port, workers=2, log_path=tmp_path / "s.log",
                          env={"PROMETHEUS_MULTIPROC_DIR": str(tmp_path / "prom")})
    try:
        http = httpx.Client(base_url=server.url, timeout=60)
        http.put("/v1/tasks/PgTask", json={"latent_dim": DIM}, headers=A).raise_for_status()
        robot = {"X-API-Key": http.post("/v1/keys", json={"name": "pg-arm", "role": "robot", "robot": "pg-arm"},
                                        headers=A).json()["key"]}

        def writer(w):
            rng = np.random.default_rng(w)
            with httpx.Client(base_url=server.url, timeout=60) as h:
                for i in range(8):
                    fail = (w + i) % 3 == 0
                    recs, _ = episode_records(f"pg{w}-{i}", "PgTask", rng, 0.6 if fail else 0.3, n_steps=5,
                                              success=not fail)
                    key = {"Idempotency-Key": f"pg{w}-{i}"}
                    for _ in range(2):  # every request sent twice, as a client retrying after a timeout would
                        r = h.post("/v1/batch", json={"records": recs}, headers={**robot, **key})
                        assert r.status_code == 200, r.text
                    # All writers also append to one shared episode at once: no update may be lost.
                    shared = {"kind": "decision", "task": "PgTask", "episode": "pg-shared", "step": w * 8 + i,
                              "horizon": 1, "z_hat": rng.normal(size=DIM).tolist(), "held_out": False}
                    r = h.post("/v1/batch", json={"records": [shared]}, headers=robot)
                    assert r.status_code == 200, r.text

        with concurrent.futures.ThreadPoolExecutor(4) as pool:
            list(pool.map(writer, range(4)))
        cal = http.post("/v1/calibrations", json={"task": "PgTask", "alpha": 0.2}, headers=A)
        assert cal.status_code == 201, cal.text
        assert cal.json()["result"]["n_success"] + cal.json()["result"]["n_failure"] == 32
        workers = children(server.process.pid)
        assert len(workers) >= 2
        server.kill()
        # SIGKILL is delivered when each worker is next scheduled: allow a busy machine a few seconds.
        deadline = time.monotonic() + 10
        while [p for p in workers if alive(p)] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [p for p in workers if alive(p)], "uvicorn workers outlived their killed supervisor"
        server = start_server(pg_url, admin_key=ADMIN, port=port, log_path=tmp_path / "s.log")
        eps = {e["id"]: e for e in http.get("/v1/episodes?task=PgTask&limit=100", headers=A).json()}
        assert eps.pop("pg-shared")["n_decisions"] == 32
        assert len(eps) == 32 and all(e["n_decisions"] == 5 and e["n_scored"] == 5 for e in eps.values())
        assert http.get("/v1/report", headers=A).json()["tasks"][0]["task"] == "PgTask"
        http.close()
    finally:
        server.stop()


def test_two_servers_on_one_postgres_lose_no_update_and_scale(pg_url, capsys):
    """The bench's PostgreSQL mode: two server processes share the database; every episode's counters agree
    with its stored rows afterwards (no update lost to the other process)."""
    from monitor_service.bench import run_bench

    out = run_bench(dim=16, seconds=1.0, concurrency=4, batch=8, batch_concurrency=2, client_decisions=0,
                    database_url=pg_url, servers=2, floor=False)
    check = out["postgres_check"]
    assert check["mismatched_episodes"] == 0 and check["decisions"] > 0
    sent = sum(m["service"]["decisions"] for m in out["modes"].values())
    assert check["decisions"] >= sent   # every acknowledged decision is stored (earlier tests' rows add to it)
    assert "2 server process(es)" in capsys.readouterr().out


def test_named_scores_gaps_and_resolved_alerts_on_postgres(pg_url, tmp_path):
    """The JSON columns (scores, signal state, gap steps, task signals) and the alert life cycle on PostgreSQL,
    across a restart that reloads the episode state from the rows."""
    from monitor_testkit import records_with_scores

    rng = np.random.default_rng(5)
    A = {"X-API-Key": ADMIN}
    with start_server(pg_url, admin_key=ADMIN, log_path=tmp_path / "a.log") as server, \
            httpx.Client(base_url=server.url, timeout=60) as http:
        http.put("/v1/tasks/Sig", json={"latent_dim": DIM, "signals": ["stac"]}, headers=A).raise_for_status()
        robot = {"X-API-Key": http.post("/v1/keys", json={"name": "pg-sig", "role": "robot", "robot": "arm9"},
                                        headers=A).json()["key"]}
        for i in range(30):
            ok = i % 3 != 0
            stac = np.exp(rng.normal(0, 0.3, 10) + (0 if ok else np.linspace(0, 2, 10)))
            recs = records_with_scores(f"sig-{i}", "Sig", rng, None, {"stac": stac}, success=ok)
            assert http.post("/v1/batch", json={"records": recs}, headers=robot).status_code == 200
        cal = http.post("/v1/calibrations", json={"task": "Sig", "signals": ["stac"], "alpha": 0.2,
                                                  "n_bootstrap": 200, "n_permutation": 200}, headers=A)
        assert cal.status_code == 201, cal.text
        first = records_with_scores("sig-live", "Sig", rng, None, {"stac": np.array([0.5, 9.0])}, held_out=False,
                                    steps=[0, 16])   # step 8 missing: a gap
        assert http.post("/v1/batch", json={"records": first}, headers=robot).status_code == 200
    with start_server(pg_url, admin_key=ADMIN, log_path=tmp_path / "b.log") as server, \
            httpx.Client(base_url=server.url, timeout=60) as http:   # a fresh process: state read from the rows
        more = records_with_scores("sig-live", "Sig", rng, None, {"stac": np.array([9.0, 9.0])}, held_out=False,
                                   steps=[24, 32], success=False)
        r = http.post("/v1/batch", json={"records": more}, headers=robot)
        assert r.status_code == 200 and len(r.json()["alerts_raised"]) == 1
        ep = http.get("/v1/episodes/sig-live", headers=A).json()
        assert ep["gaps"] == 1 and ep["gap_steps"] == [8] and ep["detector"] == "stac band"
        assert [d["scores"] for d in ep["decisions"]] == [{"stac": 0.5}, {"stac": 9.0}, {"stac": 9.0}, {"stac": 9.0}]
        alert = http.get("/v1/alerts", params={"task": "Sig"}, headers=A).json()[0]
        assert alert["state"] == "resolved" and alert["resolution"] == "failure" and alert["signals"] == "stac"
