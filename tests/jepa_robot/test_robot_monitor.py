"""`jepa-policy robot --monitor-url`: every decision's z_hat and named failure scores, each target frame's latent
and the outcome reach a real monitor service over HTTP from the synchronous robot loop."""
from __future__ import annotations

import json
import secrets

import httpx
import pytest

from jepa_envs.datasets.hdf5 import load_dataset
from jepa_policy.cli import main
from jepa_policy.train import load_config, train
from monitor_service.server import provision, start_server

SIGNALS = ["mahalanobis", "pca_kmeans", "rnd", "stac"]


@pytest.fixture
def monitor(tmp_path):
    admin = secrets.token_urlsafe(16)
    server = start_server(f"sqlite:///{tmp_path / 'monitor.db'}", admin_key=admin, log_path=tmp_path / "monitor.log")
    yield server, admin
    server.stop()


def test_robot_loop_sends_decisions_scores_targets_and_outcome(robot, monitor, pusht_demo_file, tmp_path):
    server, admin = monitor
    demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
    checkpoint = train(load_config("PushT", "quick", out_dir=str(tmp_path / "train"), steps=2, warmup_steps=0),
                       demos)["checkpoint"]
    assert main(["fit-detectors", "--checkpoint", str(checkpoint), "--dataset", str(pusht_demo_file), "--samples",
                 "200", "--device", "cpu"]) == 0
    key = provision(server.url, admin, {"PushT": None}, robot="arm-1")
    http = httpx.Client(base_url=server.url, headers={"X-API-Key": admin})
    assert http.put("/v1/tasks/PushT", json={"signals": SIGNALS}).status_code == 200
    key_file = tmp_path / "monitor.key"
    key_file.write_text(key)
    key_file.chmod(0o600)
    bridge = robot.bridge(chunk_budget=3, image_size=32)
    out = tmp_path / "summary.json"
    assert main(["robot", "--address", bridge.control_endpoint, "--checkpoint", str(checkpoint), "--episodes", "1",
                 "--no-wait", "--out", str(out), "--monitor-url", server.url, "--monitor-key-file", str(key_file),
                 "--robot", "arm-1"]) == 0
    summary = json.loads(out.read_text())
    assert summary["monitor"]["delivered"] and summary["monitor"]["rejected"] == 0
    episodes = http.get("/v1/episodes", params={"task": "PushT"}).json()
    assert len(episodes) == 1 and episodes[0]["success"] is False
    detail = http.get(f"/v1/episodes/{episodes[0]['id']}").json()
    decisions = sorted(detail["decisions"], key=lambda d: d["step"])
    assert [d["step"] for d in decisions] == [0, 8, 16]             # 3 chunks of 8 actions
    assert all(d["nmse"] is not None for d in decisions)            # every target frame arrived (step 4, 12, 20)
    first, second = decisions[0]["scores"], decisions[1]["scores"]
    assert "stac" not in first and set(first) == set(SIGNALS) - {"stac"}   # STAC needs a previous chunk
    assert set(second) == set(SIGNALS) and second["stac"] > 0


def test_robot_monitor_needs_a_key_and_the_synchronous_loop(tmp_path, pusht_demo_file, capsys):
    demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
    checkpoint = train(load_config("PushT", "quick", out_dir=str(tmp_path / "t"), steps=1, warmup_steps=0),
                       demos)["checkpoint"]
    assert main(["robot", "--checkpoint", str(checkpoint), "--monitor-url", "http://127.0.0.1:9"]) == 2
    assert "--monitor-url needs --monitor-key" in capsys.readouterr().err
    assert main(["robot", "--checkpoint", str(checkpoint), "--monitor-url", "http://127.0.0.1:9", "--monitor-key",
                 "k", "--async"]) == 2
    assert "drop --async" in capsys.readouterr().err
