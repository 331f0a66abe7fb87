"""The false-alert promise per episode length on real PushT rollouts, and live alerts over real HTTP equal to the
documented rule offline at every length.

``data/pusht_jepa_records.jsonl.gz`` is our own main job's output: ``jepa-demo`` (default mode, seed 42, at commit
e9d86c3), the JEPA arm's 128 rollouts of its ``records.jsonl`` (64 calibration, 64 live), trimmed to episode id,
phase, outcome, length and each decision's step, target step and NMSE (rounded to 6 digits). PushT failures are
300-step time-outs (37 decisions); successes end after 2-29 decisions.
"""
from pathlib import Path

import httpx
import numpy as np
import pytest
from monitor_testkit import ADMIN
from scipy.stats import binomtest

from monitor_service import rules
from monitor_service.server import start_server
from monitor_service.offline.study import load_episodes
from monitor_service.offline.synthetic import mixed_length_episodes

RECORDS = Path(__file__).parent / "data" / "pusht_jepa_records.jsonl.gz"
DIM = 8


def pusht():
    episodes, _ = load_episodes(RECORDS)
    return episodes


@pytest.mark.parametrize("alpha", [0.1, 0.2])
@pytest.mark.parametrize("kind", ["running", "band"])
def test_pusht_rollouts_false_alerts_within_the_bound_in_every_length_bin(kind, alpha):
    """Cross-fitted (each success judged by a rule calibrated without it): the false-alert count of successes,
    overall and in each length bin, is not above alpha by a one-sided binomial test at 0.001; failures alert."""
    figures = rules.cross_fit([e.scores() for e in pusht()], rules.RuleParams(kind), alpha, k=5, seed=0,
                              within_groups=True)
    assert figures["successes"] == 77 and figures["failures"] == 51 and figures["skipped_episodes"] == 0
    assert binomtest(figures["false_alerts"], 77, alpha, alternative="greater").pvalue > 1e-3
    bins = figures["false_alerts_by_length"]
    assert [(b["lo"], b["hi"]) for b in bins] == [(1, 20), (21, 40)] and sum(b["episodes"] for b in bins) == 77
    for b in bins:
        assert binomtest(b["alerts"], b["episodes"], alpha, alternative="greater").pvalue > 1e-3, b
    assert figures["true_alert_rate"] > figures["false_alert_rate"] + 0.2


def _records(task, episode, decisions, rng, held_out, success, length):
    """Ingest records whose decisions have (up to float32 rounding) the recorded NMSE; a decision whose target
    never came (the episode ended first) is sent without one."""
    recs = []
    for d in decisions:
        z = rng.normal(size=DIM)
        rec = {"kind": "decision", "task": task, "episode": episode, "step": d["step"],
               "horizon": d["target_step"] - d["step"], "held_out": held_out}
        if d["nmse"] is None:
            rec["z_hat"] = z.astype(np.float32).tolist()
            recs.append(rec)
            continue
        u = rng.normal(size=DIM)
        u /= np.linalg.norm(u)
        rec["z_hat"] = (z + u * np.sqrt(np.mean(z * z)) * np.sqrt(d["nmse"] * DIM)).astype(np.float32).tolist()
        recs += [rec, {"kind": "target", "episode": episode, "step": d["target_step"],
                       "z": z.astype(np.float32).tolist()}]
    return recs + [{"kind": "outcome", "episode": episode, "success": success, "length": length}]


def _stream(http, robot, task, episodes, rng, held_out):
    for e in episodes:
        r = http.post("/v1/batch", headers=robot, json={"records": _records(
            task, e.episode, e.decisions, rng, held_out, e.success, e.length)})
        assert r.status_code == 200, r.text


def _as_decisions(scores: rules.EpisodeScores) -> list[dict]:
    return [{"step": int(s), "target_step": int(k), "nmse": float(v)}
            for s, k, v in zip(scores.steps, scores.known_at, scores.nmse)]


def test_live_alerts_over_http_equal_the_offline_rule_at_every_length(tmp_path):
    """A real server: PushT calibrated on its calibration rollouts and a synthetic task on successes of 5-150
    decisions; every live episode's first alert (step, threshold, beyond the calibrated length or not) equals the
    rule's offline judgement, and says when no promise covers it (the lengths the episode can still end at that
    held too few calibration successes), and the episode's outcome resolves the alert as a true or a false one."""
    from monitor_service.calibration import LabelledEpisode

    rng = np.random.default_rng(0)
    eps = pusht()
    calib = [e for e in eps if "calibration" in e.episode]
    live = [e for e in eps if "live" in e.episode]
    mixed = [LabelledEpisode(s.episode, bool(s.success), _as_decisions(s), None, int(s.end_step))
             for s in mixed_length_episodes(60, 20, (5, 150), seed=3)]
    mixed_live = [LabelledEpisode("live-" + s.episode, bool(s.success), _as_decisions(s), None, int(s.end_step))
                  for s in mixed_length_episodes(40, 10, (5, 150), seed=4)]
    with start_server(f"sqlite:///{tmp_path / 'm.db'}", admin_key=ADMIN, log_path=tmp_path / "s.log") as server, \
            httpx.Client(base_url=server.url, timeout=60) as http:
        admin = {"X-API-Key": ADMIN}
        for task in ("PushT", "Mixed"):
            http.put(f"/v1/tasks/{task}", json={"latent_dim": DIM}, headers=admin).raise_for_status()
        robot = {"X-API-Key": http.post("/v1/keys", headers=admin, json={"name": "r", "role": "robot",
                                                                         "robot": "arm"}).json()["key"]}
        operator = {"X-API-Key": http.post("/v1/keys", headers=admin, json={"name": "o", "role": "operator"})
                    .json()["key"]}
        _stream(http, robot, "PushT", calib, rng, True)
        _stream(http, robot, "Mixed", mixed, rng, True)
        rule_of = {}
        for task, kind, alpha in (("PushT", "band", 0.2), ("Mixed", "running", 0.1)):
            cal = http.post("/v1/calibrations", headers=admin, json={
                "task": task, "rule": kind, "alpha": alpha, "n_bootstrap": 200, "n_permutation": 200})
            assert cal.status_code == 201, cal.text
            rule_of[task] = rules.CalibratedRule.from_dict(cal.json()["result"]["rule"])
        assert len(rule_of["Mixed"].regimes) >= 2   # the 5-150 successes give more than one length regime
        # 60 successes of 5-150 decisions: too few short ones for a promise at alpha 0.1 (9 per bin)
        assert rule_of["Mixed"].unpromised_lengths() and rule_of["Mixed"].regimes[-1].promise
        _stream(http, robot, "PushT", live, rng, False)
        _stream(http, robot, "Mixed", mixed_live, rng, False)
        alerts = http.get("/v1/alerts", params={"limit": 5000}, headers=operator).json()
        first = {}
        for a in sorted(alerts, key=lambda a: a["id"]):
            first.setdefault(a["episode_id"], a)
        checked = {"alerted": 0, "beyond": 0, "no_promise": 0}
        for task, episodes in (("PushT", live), ("Mixed", mixed_live)):
            rule = rule_of[task]
            for e in episodes:
                expected = rule.judge(e.scores())
                got = first.get(e.episode)
                assert (got is not None) == expected["alerted"], e.episode
                if got is None:
                    continue
                checked["alerted"] += 1
                checked["beyond"] += expected["beyond_calibration"]
                assert got["step"] == expected["step"], e.episode
                assert got["threshold"] == pytest.approx(rule.threshold_at(expected["decision_index"]), rel=1e-9)
                assert got["beyond_calibration"] == expected["beyond_calibration"]
                # once the episode ended, its alert says whether its length carried the promise, and why not
                assert got["no_promise"] == bool(expected["unpromised"])
                assert ("no false-alert promise" in got["note"]) == got["no_promise"]
                checked["no_promise"] += got["no_promise"]
                # the outcome arrived after the alert: resolved, as a false alert on a success
                assert got["state"] in ("resolved", "cleared")
                if got["state"] == "resolved":
                    assert got["resolution"] == ("success" if e.success else "failure")
        assert checked["alerted"] >= 10 and checked["beyond"] >= 1 and checked["no_promise"] >= 1, checked
        detail = http.get(f"/v1/episodes/{live[0].episode}", headers=operator).json()
        assert detail["calibrated_decisions"] == rule_of["PushT"].calibrated_decisions


def test_the_length_check_command_prints_its_figures_and_a_bar_on_stderr(capsys):
    """`jepa-monitor study --length-check` ran 119 s without a word; its calibrations are on a bar now."""
    import json

    from monitor_service.cli import main

    argv = ["study", "--length-check", "--draws", "3", "--fresh", "20", "--successes", "20", "--alpha", "0.2"]
    assert main([*argv, "--json"]) == 0
    out, err = capsys.readouterr()
    check = json.loads(out)
    assert check["draws"] == 3 and set(check["rules"]) == {"running, alpha 0.2", "band, alpha 0.2"}
    assert "length check: 100%" in err and "6/6" in err          # 2 rule kinds x 1 alpha x 3 calibrations
    assert main([*argv, "--no-progress"]) == 0
    out, err = capsys.readouterr()
    assert "false alerts of fresh successes in the bins the calibration promised" in out and err == ""
    assert "3 calibrations on 20 successes, 20 fresh" in out
    # mostly short calibration successes: 2 of 20 in 21-150, too few for a promise at 0.2 in any longer bin even
    # at alpha's own minimum (4); the fresh successes there are counted apart and every one of their alerts says it
    # has no promise
    assert main([*argv, "--no-progress", "--json", "--short-share", "0.9"]) == 0
    check = json.loads(capsys.readouterr().out)
    assert check["short_share"] == 0.9 and check["promise_min"] == 1
    for bins in check["rules"].values():
        assert bins[0]["unpromised_episodes"] == 0 and sum(b["unpromised_episodes"] for b in bins[1:]) > 0
        assert all(b["unpromised_alerts_flagged"] == b["unpromised_alerts"] for b in bins)
    with pytest.raises(SystemExit):
        main([*argv, "--short-share", "1.5"])
    assert "strictly between 0 and 1" in capsys.readouterr().err
