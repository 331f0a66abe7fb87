"""deploy/RUNBOOK.md is walked as written: its ``sh`` blocks run in order in one shell state, on this machine
(no Docker): start the server, create keys and use one against it, register and calibrate a task, back up,
restore. Between the blocks the test plays the robot (held-out rollouts over real HTTP) and the operator who
stops the service before a restore. promtool checks the Prometheus configuration and alert rules.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import sqlite3
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from runbook_walker import Shell, free_port, runbook_blocks

from monitor_service.client import MonitorClient

ROOT = Path(__file__).resolve().parents[2]
RUNBOOK = ROOT / "deploy" / "RUNBOOK.md"
DEPLOY = ROOT / "deploy" / "monitor"


def _send_held_out_rollouts(url: str, key: str, task: str, successes: int, failures: int) -> None:
    rng = np.random.default_rng(7)
    with MonitorClient(url, key, robot="arm1") as client:
        for i in range(successes + failures):
            success = i < successes
            episode = f"{task}-held-out-{i}"
            noise = 0.3 if success else 0.8
            for t in range(6):
                z = rng.normal(size=16)
                z_hat = z + noise * rng.normal(size=16)
                client.decision(task, episode, t, 1, z_hat, held_out=True, group=f"seed{i % 3}")
                client.target(episode, t + 1, z)
            client.outcome(episode, success, length=48)
        assert client.flush(60)
        assert client.stats.dropped == 0 and not client.stats.rejected


@pytest.mark.timeout(300)
def test_runbook_walks_on_one_host(tmp_path):
    blocks = [body for info, body in runbook_blocks(RUNBOOK.read_text()) if info == "sh"]
    assert len(blocks) == 6, "the walk below follows the RUNBOOK's sh blocks one by one"
    start, keys, add_task, calibrate, backup, restore = blocks
    port = free_port()
    shell = Shell(tmp_path, {"8765": str(port)})
    try:
        shell.run(start)
        assert shell.env("JEPA_MONITOR_DATABASE_URL") == f"sqlite:///{tmp_path}/monitor.db"
        out = shell.run(keys)
        assert json.loads(out.strip().splitlines()[-1]) == []   # the operator key works against the server
        robot_key = json.loads((tmp_path / "arm1.key.json").read_text())["key"]
        assert oct((tmp_path / "arm1.key.json").stat().st_mode)[-3:] == "600"
        shell.run(add_task)
        _send_held_out_rollouts(f"http://127.0.0.1:{port}", robot_key, "Square", successes=24, failures=12)
        out = shell.run(calibrate)
        assert "AUROC" in out and "Square" in out
        shell.run(backup)
        assert (tmp_path / "monitor-backup.db").is_file()
        # after the backup: a key that the restore must take away again
        shell.run("jepa-monitor keys create --name late --role operator > late.key.json")
        # a restore under the live server is refused, and the database is left as it was
        with pytest.raises(AssertionError, match="a monitor server is serving"):
            shell.run(restore)
        names = {r[0] for r in sqlite3.connect(tmp_path / "monitor.db").execute("SELECT name FROM api_keys")}
        assert "late" in names
    finally:
        pid = subprocess.run(["pgrep", "-f", f"jepa-monitor serve --port {port}"], capture_output=True, text=True)
        for p in pid.stdout.split():   # the operator stops the service before a restore
            os.kill(int(p), signal.SIGTERM)
        deadline = time.monotonic() + 30
        while subprocess.run(["pgrep", "-f", f"jepa-monitor serve --port {port}"]).returncode == 0:
            assert time.monotonic() < deadline, "the monitor did not stop within 30 s of SIGTERM"
            time.sleep(0.1)
    shell.run(restore)
    names = {r[0] for r in sqlite3.connect(tmp_path / "monitor.db").execute("SELECT name FROM api_keys")}
    assert {"arm1", "alice"} <= names and "late" not in names, "the restore brings back the backup's state"
    calibrations = sqlite3.connect(tmp_path / "monitor.db").execute("SELECT count(*) FROM calibrations").fetchone()
    assert calibrations == (1,)


def test_restore_refuses_a_file_that_is_not_a_monitor_backup(tmp_path):
    from monitor_service.cli import main

    junk = tmp_path / "junk.db"
    sqlite3.connect(junk).execute("CREATE TABLE t (x)").connection.commit()
    with pytest.raises(SystemExit, match="not a monitor database"):
        main(["--database-url", f"sqlite:///{tmp_path}/m.db", "db", "restore", str(junk)])
    (tmp_path / "text.db").write_text("hello")
    with pytest.raises(SystemExit, match="not an SQLite database"):
        main(["--database-url", f"sqlite:///{tmp_path}/m.db", "db", "restore", str(tmp_path / "text.db")])
    with pytest.raises(SystemExit, match="pg_dump"):
        main(["--database-url", "postgresql+psycopg://u@h/db", "db", "backup", str(tmp_path / "b.db")])


def test_console_blocks_name_real_files_and_commands():
    """The Docker blocks cannot run here; what they name must exist and agree with the compose file."""
    text = RUNBOOK.read_text()
    console = "\n".join(body for info, body in runbook_blocks(text) if info == "console")
    for path in re.findall(r"deploy/monitor/[\w./-]+", console):
        if path.endswith((".env", "prometheus_token")):
            continue   # made by the operator
        assert (ROOT / path).exists(), path
    compose = yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())
    for service in re.findall(r"(?:up -d(?: --build)?|exec(?: -T)?|stop|start) ([a-z ]+?)(?:\s|$)", console):
        for name in service.split():
            if name in ("jepa-monitor", "pg_dump", "pg_restore", "-U"):
                continue
            assert name in compose["services"], name
    token_step = console.index("secrets/prometheus_token")
    started = console.rindex("--env-file deploy/monitor/.env up -d")
    assert console.index("up -d --build db monitor") < token_step < started
    assert "deploy/monitor/.env" in (ROOT / ".gitignore").read_text()
    assert "chown monitor:monitor /data" in (DEPLOY / "Dockerfile").read_text()


def _promtool() -> str:
    found = shutil.which("promtool") or (ROOT / ".cache" / "tools" / "promtool")
    if not Path(found).exists():
        pytest.fail("promtool is missing: `bash scripts/setup.sh` unpacks it into .cache/tools")
    return str(found)


def test_promtool_accepts_the_prometheus_config_and_rules(tmp_path):
    promtool = _promtool()
    rules = subprocess.run([promtool, "check", "rules", str(DEPLOY / "alert_rules.yml")], capture_output=True,
                           text=True)
    assert rules.returncode == 0 and "4 rules found" in rules.stdout, rules.stdout + rules.stderr
    # the config as Prometheus sees it in the container: its mounted files at their container paths
    config = (DEPLOY / "prometheus.yml").read_text()
    (tmp_path / "monitor_token").write_text("secret")
    shutil.copy(DEPLOY / "alert_rules.yml", tmp_path / "alert_rules.yml")
    config = config.replace("/etc/prometheus/", f"{tmp_path}/")
    (tmp_path / "prometheus.yml").write_text(config)
    checked = subprocess.run([promtool, "check", "config", str(tmp_path / "prometheus.yml")], capture_output=True,
                             text=True)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    (tmp_path / "monitor_token").unlink()   # what happened when the token was made after `up`
    missing = subprocess.run([promtool, "check", "config", str(tmp_path / "prometheus.yml")], capture_output=True,
                             text=True)
    assert missing.returncode != 0


def test_promtool_unit_tests_of_the_alert_rules(tmp_path):
    """The alerts fire on the series they are written for (promtool's rule unit tests)."""
    promtool = _promtool()
    shutil.copy(DEPLOY / "alert_rules.yml", tmp_path / "alert_rules.yml")
    (tmp_path / "tests.yml").write_text(yaml.safe_dump({
        "rule_files": ["alert_rules.yml"],
        "evaluation_interval": "15s",
        "tests": [{
            "interval": "15s",
            "input_series": [
                {"series": 'up{job="jepa-monitor", instance="monitor:8765"}', "values": "1 1 0 0 0 0 0 0 0"},
                {"series": 'jepa_monitor_open_alerts{task="Square"}', "values": "0 1 1 1 1 1 1 1 1 1 1 1"},
            ],
            "alert_rule_test": [
                {"eval_time": "2m", "alertname": "JepaMonitorDown",
                 "exp_alerts": [{"exp_labels": {"severity": "page", "job": "jepa-monitor",
                                                "instance": "monitor:8765"},
                                 "exp_annotations": {"summary": "The JEPA monitor does not answer /metrics"}}]},
                {"eval_time": "2m45s", "alertname": "JepaInterventionAlertsOpen",
                 "exp_alerts": [{"exp_labels": {"severity": "ticket", "task": "Square"},
                                 "exp_annotations": {"summary": "Square has open intervention alerts; acknowledge "
                                                                "them on the dashboard"}}]},
            ],
        }],
    }))
    out = subprocess.run([promtool, "test", "rules", str(tmp_path / "tests.yml")], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
