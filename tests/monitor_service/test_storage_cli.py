"""Migrations, the encoding, and the offline CLI (calibrate, report, keys, tasks, db)."""
import json

import numpy as np
import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from fastapi.testclient import TestClient
from monitor_testkit import ADMIN, episode_records, make_settings, new_key, post_batch, register_task
from sqlalchemy import text

from monitor_service import db
from monitor_service.app import create_app
from monitor_service.cli import main
from monitor_service.encoding import BodyError, decode_body, pack, unpack


def test_migrations_reach_head_idempotently_and_match_models(tmp_path):
    engine = db.make_engine(f"sqlite:///{tmp_path / 'm.db'}")
    assert db.current_revision(engine) is None
    db.upgrade(engine)
    db.upgrade(engine)
    assert db.current_revision(engine) == db.head_revision() == "0006"
    with engine.connect() as conn:
        assert compare_metadata(MigrationContext.configure(conn), db.Base.metadata) == []
        assert conn.execute(text("PRAGMA journal_mode")).scalar() == "wal"


def test_encoding_round_trip_and_errors():
    z = np.random.default_rng(0).normal(size=7).astype(np.float32)
    out = unpack(pack({"a": z, "b": [1, "x"]}))
    assert out["a"].dtype == np.float32 and np.array_equal(out["a"], z) and out["b"] == [1, "x"]
    assert pack({"z": z})[-28:] == z.astype("<f4").tobytes()  # raw little-endian bytes, no pickle
    with pytest.raises(BodyError, match="float32"):
        unpack(pack({"z": {"dtype": "<f8", "shape": [1], "data": b"\0" * 8}}))
    with pytest.raises(TypeError, match="cannot encode"):
        pack({"z": object()})
    with pytest.raises(BodyError, match="malformed JSON"):
        decode_body(b"{", "application/json")


def test_cli_offline_calibrate_report_keys_tasks(tmp_path, capsys):
    settings = make_settings(tmp_path)
    url = ["--database-url", settings.database_url]
    assert main(url + ["db", "upgrade"]) == 0
    assert "revision 0006" in capsys.readouterr().out
    assert main(url + ["tasks", "add", "Square", "Coffee", "--latent-dim", "16"]) == 0
    assert main(url + ["keys", "create", "--name", "arm9", "--role", "robot", "--robot", "arm9"]) == 0
    key = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["key"]
    with TestClient(create_app(settings)) as c:
        robot = {"X-API-Key": key}
        rng = np.random.default_rng(5)
        for i in range(30):
            fail = i % 3 == 0
            records, _ = episode_records(f"e{i}", "Square", rng, 0.6 if fail else 0.3, n_steps=5, success=not fail)
            post_batch(c, robot, records, key=f"k{i}")
    assert main(url + ["calibrate", "--task", "Square", "--n-bootstrap", "300", "--n-permutation", "300"]) == 0
    out = capsys.readouterr().out
    assert "AUROC" in out and "n_success=20, n_failure=10" in out and "alert rule band (window 5, debounce 2)" in out
    assert "at alpha=0.1" in out and "false alerts on successes" in out and "control persistence: n/a" in out
    assert main(url + ["report"]) == 0
    out = capsys.readouterr().out
    assert "Square" in out and "uncalibrated (no alerts): Coffee" in out and "WARNING" in out
    assert main(url + ["report", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["tasks"][0]["task"] == "Square" and rep["tasks"][0]["n_failure"] == 10
    assert main(url + ["calibrate", "--task", "Nope"]) == 2
    assert "not registered" in capsys.readouterr().err
    assert main(url + ["db", "prune", "--older-than-days", "1"]) == 0
    assert "removed 0 idempotency keys" in capsys.readouterr().out
    assert main(url + ["db", "prune", "--older-than-days", "0"]) == 0
    assert "removed 30 idempotency keys" in capsys.readouterr().out
    assert main(url + ["keys", "revoke", "1"]) == 0
    assert main(url + ["keys", "list"]) == 0
    assert "revoked" in capsys.readouterr().out
    assert main(url + ["keys", "revoke", "999"]) == 2     # the fix on the command line, not an HTTP route
    assert capsys.readouterr().err.strip() == ("jepa-monitor: error: API key id 999 does not exist; list them "
                                               "with `jepa-monitor keys list`")


def test_admin_key_bootstrap_refuses_a_revoked_secret(tmp_path):
    settings = make_settings(tmp_path)
    with TestClient(create_app(settings)) as c:
        register_task(c, "Square")
        new_key(c, "op", "operator")
        keys = c.get("/v1/keys", headers={"X-API-Key": ADMIN}).json()
        admin_id = next(k["id"] for k in keys if k["role"] == "admin")
        assert c.delete(f"/v1/keys/{admin_id}", headers={"X-API-Key": ADMIN}).status_code == 200
    with pytest.raises(ValueError, match="revoked or non-admin"):
        create_app(settings)


# (argv, a piece of the one-line answer naming the fix); {d} is an empty folder that must stay empty
BAD_DATABASES = [
    (["--database-url", "sqlite:///{d}/mistyped.db", "keys", "list"], "db upgrade"),
    (["--database-url", "sqlite:///{d}/mistyped.db", "db", "current"], "db upgrade"),
    (["--database-url", "sqlite:///{d}/mistyped.db", "serve", "--port", "9"], "serve --create"),
    (["--database-url", "sqlite:///{d}/no/such/folder/m.db", "db", "upgrade"], "mkdir -p {d}/no/such/folder"),
    (["--database-url", "sqlite:///{d}/no/such/folder/m.db", "serve", "--create"], "mkdir -p"),
    (["--database-url", "postgresql+psycopg2://monitor:secret@127.0.0.1:9/monitor", "db", "upgrade"],
     "Write postgresql+psycopg://monitor:***@127.0.0.1:9/monitor"),
    (["--database-url", "postgresql+psycopg2://monitor@127.0.0.1:9/monitor?password=secret", "db", "upgrade"],
     "Write postgresql+psycopg://monitor@127.0.0.1:9/monitor?password=***"),
    (["--database-url", "postgresql+psycopg://monitor@127.0.0.1:9/monitor", "db", "upgrade"],
     "that the database server runs"),
    (["--database-url", "postgresql://monitor@127.0.0.1:9/monitor", "db", "upgrade"], "that the database server runs"),
    (["--database-url", "postgres://monitor@127.0.0.1:9/monitor", "db", "upgrade"], "that the database server runs"),
    (["--database-url", "postgresql+asyncpg://monitor@127.0.0.1:9/monitor", "db", "upgrade"],
     "psycopg 3 (synchronous"),
    (["--database-url", "sqlite:/m.db", "db", "upgrade"], "not a valid URL"),
    (["--database-url", "sqlite:/m.db", "tasks", "list"], "sqlite:////absolute/path.db"),
]


@pytest.mark.parametrize("argv, fix", BAD_DATABASES, ids=[" ".join(a)[:70] for a, _ in BAD_DATABASES])
def test_a_bad_database_is_refused_in_one_line_and_nothing_is_created(tmp_path, monkeypatch, capsys, argv, fix):
    folder = tmp_path / "d"
    folder.mkdir()
    monkeypatch.chdir(folder)   # a relative default would land here
    monkeypatch.setenv("JEPA_MONITOR_DATABASE_URL", "")   # restored afterwards (serve exports its URL)
    monkeypatch.delenv("JEPA_MONITOR_DATABASE_URL")
    code = main([a.format(d=folder) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and fix.format(d=folder) in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert list(folder.iterdir()) == [], "a refused database must leave nothing behind"


SECRET_URLS = [
    "postgresql+psycopg2://monitor:s3cret@127.0.0.1:9/monitor",           # another driver
    "postgresql+psycopg2://monitor@127.0.0.1:9/monitor?password=s3cret",  # the password as libpq's parameter
    "mysql://monitor:s3cret@127.0.0.1:9/monitor",                         # neither SQLite nor PostgreSQL
    "postgresql+psycopg://monitor:s3cret@127.0.0.1:9/monitor",            # no server there
    "postgresql+psycopg://monitor@127.0.0.1:9/monitor?sslpassword=s3cret",
]


@pytest.mark.parametrize("url", SECRET_URLS)
def test_a_refused_database_url_never_prints_its_password(tmp_path, monkeypatch, capsys, url):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("JEPA_MONITOR_DATABASE_URL", raising=False)
    assert main(["--database-url", url, "db", "upgrade"]) == 2
    err = capsys.readouterr().err
    assert "s3cret" not in err and len(err.strip().splitlines()) == 1, err


def test_db_upgrade_or_serve_create_make_the_database(tmp_path, capsys):
    url = f"sqlite:///{tmp_path / 'new.db'}"
    assert main(["--database-url", url, "db", "upgrade"]) == 0 and (tmp_path / "new.db").is_file()
    assert main(["--database-url", url, "keys", "list"]) == 0


def test_an_unknown_setting_variable_is_a_warning_naming_the_setting(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("JEPA_MONITOR_DB", f"sqlite:///{tmp_path / 'meant.db'}")
    monkeypatch.setenv("JEPA_MONITOR_DATABASE_URL", "")
    monkeypatch.delenv("JEPA_MONITOR_DATABASE_URL")
    monkeypatch.chdir(tmp_path)
    assert main(["db", "upgrade"]) == 0
    err = capsys.readouterr().err
    assert "JEPA_MONITOR_DB is not a setting of the monitor and is ignored; did you mean " \
           "JEPA_MONITOR_DATABASE_URL?" in err
    monkeypatch.setenv("JEPA_MONITOR_ALHPA", "0.2")
    assert main(["--database-url", f"sqlite:///{tmp_path / 'jepa_monitor.db'}", "tasks", "list"]) == 0
    assert "did you mean JEPA_MONITOR_ALPHA?" in capsys.readouterr().err


def test_tasks_add_refuses_another_latent_dim_for_an_existing_task(tmp_path, capsys):
    """`tasks add Square PushT --latent-dim 1024` left an existing 8-d PushT at 8 without a word; now the command
    is refused (nothing added) naming the fix, and adding only signals to it still works."""
    url = ["--database-url", make_settings(tmp_path).database_url]
    assert main(url + ["db", "upgrade"]) == 0
    assert main(url + ["tasks", "add", "PushT", "--latent-dim", "8"]) == 0
    capsys.readouterr()
    assert main(url + ["tasks", "add", "Square", "PushT", "--latent-dim", "1024", "--signals", "stac,rnd"]) == 2
    err = capsys.readouterr().err
    assert "task PushT exists with latent_dim 8, not 1024" in err and "another name (e.g. PushT-1024)" in err
    assert main(url + ["tasks", "list"]) == 0
    assert capsys.readouterr().out.splitlines() == ["PushT\tlatent_dim=8\tsignals=-"]   # Square not added either
    assert main(url + ["tasks", "add", "PushT", "--latent-dim", "8", "--signals", "stac"]) == 0
    assert "PushT\tlatent_dim=8\tsignals=stac" in capsys.readouterr().out


def test_bodies_with_a_duplicated_key_or_deep_nesting_are_refused_with_a_reason():
    """A JSON object naming a key twice was taken (the last value won); a 100,000-deep msgpack body was refused
    as 'malformed msgpack body ()'. A colon inside a string still takes the fast path's answer."""
    for body in (b'{"records": [{"kind": "decision", "step": 1, "step": 2}]}',
                 b'{"records": [], "records" : [1]}',                 # a space before the colon
                 b'{"t": "12:00", "a": 1, "a": 2}',                   # a colon in a string as well
                 b'{"a": NaN, "a": 1}'):                              # the standard parser's path
        with pytest.raises(BodyError, match="names the key '(step|records|a)' twice; send each field once"):
            decode_body(body, "application/json")
    assert decode_body(b'{"t": "12:00", "a": [1, {"b": 2}]}', "application/json") == {"t": "12:00",
                                                                                        "a": [1, {"b": 2}]}
    with pytest.raises(BodyError, match=r"malformed msgpack body \(nested too deeply"):
        decode_body(b"\x91" * 100_000 + b"\x01", "application/x-msgpack")


def test_a_nan_setting_is_refused_as_not_finite(monkeypatch, capsys):
    monkeypatch.setenv("JEPA_MONITOR_ALPHA", "nan")   # said "Input should be less than 1"
    assert main(["--database-url", "sqlite:///nowhere.db", "db", "current"]) == 2
    assert "alpha must be a finite number in [0.001, 1), got 'nan'" in capsys.readouterr().err
