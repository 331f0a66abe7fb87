"""`jepa-monitor replay`: recorded rollouts with latents into a real server over HTTP, as a robot sends them; the
service's NMSE and persistence NMSE equal those recomputed from the file's latents, the held-out ones calibrate
and the live ones are alerted on; bad files and missing keys are one-line errors."""
import json

import httpx
import numpy as np
import pytest
from monitor_testkit import ADMIN, latent_records, write_records

from monitor_service.cli import main
from monitor_service.scoring import nmse
from monitor_service.server import start_server

DIM = 16   # latent_records' default


def test_replay_calibrates_then_alerts_with_the_files_own_numbers(tmp_path, monkeypatch, capsys):
    rows = latent_records(40, 16, seed=3) + [{**r, "arm": "mip"} for r in latent_records(2, 0, seed=4)]
    path = write_records(tmp_path / "decisions.jsonl.gz", rows)
    with start_server(f"sqlite:///{tmp_path / 'm.db'}", admin_key=ADMIN, log_path=tmp_path / "s.log") as server, \
            httpx.Client(base_url=server.url, timeout=60) as http:
        admin = {"X-API-Key": ADMIN}
        http.put("/v1/tasks/Lift", json={"latent_dim": DIM, "signals": ["stac"]}, headers=admin).raise_for_status()
        robot_key = http.post("/v1/keys", headers=admin, json={"name": "r", "role": "robot", "robot": "arm"}
                              ).json()["key"]
        operator = {"X-API-Key": http.post("/v1/keys", headers=admin, json={"name": "o", "role": "operator"})
                    .json()["key"]}
        monkeypatch.setenv("JEPA_POLICY_MONITOR_KEY", robot_key)
        argv = ["replay", str(path), "--task", "Lift", "--url", server.url, "--where", "arm=jepa",
                "--held-out", "0.5", "--prefix", "lift-", "--signals", "stac", "--json"]
        assert main(argv) == 0
        summary = json.loads(capsys.readouterr().out)
        jepa = [r for r in rows if r["arm"] == "jepa"]
        assert summary["episodes"] == 56 and summary["held_out"] == 28 and summary["rejected"] == []
        assert summary["decisions"] == sum(len(r["decisions"]) for r in jepa)
        assert summary["targets"] == sum("z_real" in d for r in jepa for d in r["decisions"])
        listed = http.get("/v1/episodes", params={"task": "Lift", "limit": 1000}, headers=operator).json()
        assert len(listed) == 56
        # the service scored each decision from the latents sent: the file's numbers, to float32 rounding
        for row in jepa[:3] + jepa[-3:]:
            detail = http.get(f"/v1/episodes/lift-{row['seed']}", headers=operator).json()
            assert detail["success"] == row["success"] and detail["length"] == row["length"]
            got = {d["step"]: d for d in detail["decisions"]}
            for d in row["decisions"]:
                if "z_real" in d:
                    assert got[d["step"]]["nmse"] == pytest.approx(d["nmse"], rel=1e-5)
                    assert got[d["step"]]["nmse_persistence"] == pytest.approx(
                        nmse(np.array(d["z_now"]), np.array(d["z_real"])), rel=1e-5)
                    assert got[d["step"]]["scores"]["stac"] == pytest.approx(d["scores"]["stac"], rel=1e-6)
                else:
                    assert got[d["step"]]["nmse"] is None
        # a wrong task: the first episode is refused whole, and nothing more is sent (one line)
        assert main(["replay", str(path), "--task", "Nope", "--url", server.url, "--prefix", "x-",
                     "--no-progress"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "refused every record of the first episode" in err, err
        assert len(http.get("/v1/episodes", params={"limit": 1000}, headers=operator).json()) == 56
        # the held-out half calibrates the task; replaying the file again under new ids sends it all live
        cal = http.post("/v1/calibrations", headers=admin, json={"task": "Lift", "rule": "running",
                                                                 "n_bootstrap": 100, "n_permutation": 100})
        assert cal.status_code == 201, cal.text
        result = cal.json()["result"]
        # every held-out episode counted (those too short for the five-decision early score skipped by it)
        assert result["n_success"] + result["n_failure"] + result["skipped_episodes"] == 28
        assert main(["replay", str(path), "--task", "Lift", "--url", server.url, "--where", "arm=jepa",
                     "--held-out", "0", "--prefix", "again-"]) == 0
        assert "56 episodes (0 held out for calibration, 56 live)" in capsys.readouterr().out
        # --part live sends only the episodes after the held-out ones
        assert main(["replay", str(path), "--task", "Lift", "--url", server.url, "--where", "arm=jepa",
                     "--held-out", "50", "--part", "live", "--prefix", "tail-", "--no-progress"]) == 0
        assert "6 episodes (0 held out for calibration, 6 live)" in capsys.readouterr().out
        alerts = http.get("/v1/alerts", params={"limit": 1000}, headers=operator).json()
        alerted = {a["episode_id"] for a in alerts if a["episode_id"].startswith("again-")}
        failed = {f"again-{r['seed']}" for r in jepa if not r["success"]}
        assert len(alerted & failed) >= 12, "the failures predict their future worse: most alert"
        assert len(alerted - failed) <= 10


def test_replay_errors_are_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("JEPA_POLICY_MONITOR_KEY", raising=False)
    good = write_records(tmp_path / "r.jsonl.gz", latent_records(2, 0, seed=1))
    no_latents = tmp_path / "plain.jsonl"
    no_latents.write_text(json.dumps({"success": True, "decisions": [{"step": 0, "nmse": 0.1}]}) + "\n")
    bad = tmp_path / "bad.jsonl"
    bad.write_text("{not json\n")
    not_gzip = tmp_path / "plain.jsonl.gz"
    not_gzip.write_text("{}\n")
    cases = [
        (["replay", str(tmp_path / "none.jsonl"), "--task", "T"], "does not exist; write one with `jepa-policy eval"),
        (["replay", str(no_latents), "--task", "T", "--api-key", "k"], "hold no latents (z_hat)"),
        (["replay", str(bad), "--task", "T", "--api-key", "k"], "bad.jsonl:1: not JSON"),
        (["replay", str(good), "--task", "T"], "give the robot key"),
        (["replay", str(good), "--task", "T", "--api-key", "k", "--where", "arm"], "give FIELD=VALUE"),
        (["replay", str(good), "--task", "T", "--api-key", "k", "--where", "arm=mip"], "no episode records with"),
        (["replay", str(not_gzip), "--task", "T", "--api-key", "k"], "unreadable after line 0 (BadGzipFile"),
        (["replay", str(good), "--task", "T", "--api-key", "k", "--url", "http://127.0.0.1:9"],
         "no monitor answers at http://127.0.0.1:9"),
        (["tasks-study", "--task", f"T={not_gzip}"], "unreadable after line 0"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, (argv, err)
    with pytest.raises(SystemExit):
        main(["replay", str(good), "--task", "T", "--held-out", "1.5"])
    assert "a count >= 0 or a share" in capsys.readouterr().err


def test_tasks_study_calibrates_each_task_in_one_service_and_shows_what_pooling_does(tmp_path, capsys):
    """Two tasks of different latent sizes whose successes predict their future with different errors: each
    calibrated on its own held-out half, the service's live alerts equal the rule offline, and one threshold
    pooled over both over-alerts the noisier task's successes and misses the quieter task's failures."""
    quiet = write_records(tmp_path / "quiet.jsonl.gz", latent_records(120, 40, seed=5, dim=8, noise=(0.2, 0.5)))
    noisy = write_records(tmp_path / "noisy.jsonl.gz", latent_records(120, 40, seed=6, dim=24, noise=(0.6, 1.2)))
    out = tmp_path / "study"
    argv = ["tasks-study", "--task", f"Quiet={quiet}", "--task", f"Noisy={noisy}", "--alpha", "0.1"]
    assert main([*argv, "--out", str(out / "s.png")]) == 2   # checked before the work: no such folder
    assert "give a file in an existing folder" in capsys.readouterr().err
    out.mkdir()
    assert main([*argv, "--out", str(out / "tasks_study.json"), "--out", str(out / "tasks_study.md"),
                 "--out", str(out / "tasks_nmse.png")]) == 0
    captured = capsys.readouterr()
    table = captured.out
    assert "replay Quiet: 100%" in captured.err   # its bars
    assert "| Quiet |" in table and "| Noisy |" in table and "| Noisy | dropped |" in table
    study = json.loads((out / "tasks_study.json").read_text())
    q, n = study["tasks"]["Quiet"], study["tasks"]["Noisy"]
    assert q["latent_dim"] == 8 and n["latent_dim"] == 24 and q["held_out"] == n["held_out"] == 80
    for t in (q, n):
        assert t["service"]["agrees_with_offline"], t["service"]
        assert t["live"]["successes"] + t["live"]["failures"] == 80 and t["live"]["failures"] >= 10
        own = t["own_threshold"]["false_alerts"]
        assert own["k"] <= 16, own     # about alpha of ~60 (binomial: P(k > 16 | n=70, p=0.1) < 1e-3)
    assert q["calibration"]["threshold"] < study["pooled"]["threshold"] < n["calibration"]["threshold"]
    assert n["pooled_threshold"]["false_alerts"]["k"] > n["own_threshold"]["false_alerts"]["k"] + 5
    assert q["pooled_threshold"]["detection"]["k"] < q["own_threshold"]["detection"]["k"]
    assert set(q["own_threshold"]["detection_by_kind"]) == {"never_grasped", "dropped"}
    assert (out / "tasks_nmse.png").stat().st_size > 10_000 and "tasks_nmse.png" in (out / "tasks_study.md").read_text()
