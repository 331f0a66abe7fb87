"""The service alerts exactly as its calibrated rule says: live alerts against the pure rule, stale settings,
the controls, detection figures, metrics and the early score of out-of-order decisions."""
import json
import re

import numpy as np
import pytest
from fastapi.testclient import TestClient
from monitor_testkit import ADMIN, make_settings, new_key, post_batch, records_for_nmse, register_task
from sqlalchemy import select

from monitor_service import rules
from monitor_service.app import create_app
from monitor_service.db import CalibrationRow, Episode
from monitor_service.offline.synthetic import synthetic_episodes

ADMIN_H = {"X-API-Key": ADMIN}


def _calibration_set(c, robot, rng, n_success=24, n_failure=12, decisions=12, z_now=False, seed=0):
    """Held-out synthetic episodes (known law) sent through the API, with lengths and optionally z_now."""
    eps = synthetic_episodes(n_success, n_failure, decisions, seed=seed)
    for e in eps:
        pers = (np.asarray(e.nmse) * rng.uniform(0.5, 2.0, e.nmse.size)).tolist() if z_now else None
        recs = records_for_nmse(e.episode, "Square", rng, e.nmse.tolist(), e.steps.tolist(), success=e.success,
                                length=e.end_step, persistence=pers)
        assert post_batch(c, robot, recs).status_code == 200
    return eps


@pytest.mark.parametrize("kind", ["band", "running"])
def test_live_alerts_are_exactly_the_calibrated_rules_alerts(client, robot, operator, admin, kind):
    register_task(client, "Square")
    rng = np.random.default_rng(1)
    _calibration_set(client, robot, rng)
    cal = client.post("/v1/calibrations", json={"task": "Square", "rule": kind, "n_bootstrap": 200,
                                                "n_permutation": 200}, headers=admin)
    assert cal.status_code == 201, cal.text
    rule = rules.CalibratedRule.from_dict(cal.json()["result"]["rule"])
    assert rule.params.kind == kind and cal.json()["rule"] == kind
    live = synthetic_episodes(15, 15, 12, seed=99)
    for e in live:
        e.episode = "live-" + e.episode
        # decisions arrive one at a time, each followed later by its target, as from a robot loop
        for rec in records_for_nmse(e.episode, "Square", rng, e.nmse.tolist(), e.steps.tolist(), held_out=False):
            assert post_batch(client, robot, [rec]).status_code == 200
    alerts = client.get("/v1/alerts?limit=1000", headers=operator).json()
    first = {}
    for a in sorted(alerts, key=lambda a: a["id"]):
        first.setdefault(a["episode_id"], a)
    for e in live:
        expected = rule.judge(e)
        got = first.get(e.episode)
        assert (got is not None) == expected["alerted"], e.episode
        if got is not None:
            threshold = rule.threshold_at(expected["decision_index"])
            assert got["step"] == expected["step"] and got["threshold"] == pytest.approx(threshold)
            detail = client.get(f"/v1/episodes/{e.episode}", headers=operator).json()
            assert detail["rule"] == kind and detail["threshold"] == pytest.approx(rule.threshold)
            assert [p["value"] for p in detail["risk"]] == pytest.approx(rule.running(e).tolist(), rel=1e-4)
            assert [p["threshold"] for p in detail["risk"]] == pytest.approx(rule.thresholds(12).tolist())
    assert sum(not e.success for e in live if e.episode in first) >= 5   # the drifting failures alert
    assert sum(e.success for e in live if e.episode in first) <= 3


def test_changing_window_or_debounce_voids_the_calibration_until_recalibrated(tmp_path):
    settings = make_settings(tmp_path, n_bootstrap=200, n_permutation=200)
    rng = np.random.default_rng(2)
    with TestClient(create_app(settings)) as c:
        register_task(c, "Square")
        robot = new_key(c, "r", "robot", "arm1")
        _calibration_set(c, robot, rng)
        assert c.post("/v1/calibrations", json={"task": "Square"}, headers=ADMIN_H).status_code == 201
    stale = make_settings(tmp_path, n_bootstrap=200, n_permutation=200, alert_debounce=3)
    with TestClient(create_app(stale)) as c:
        op = new_key(c, "op", "operator")
        bad = records_for_nmse("bad", "Square", rng, [5.0] * 10, held_out=False)
        assert post_batch(c, robot, bad).json()["alerts_raised"] == []
        ep = c.get("/v1/episodes/bad", headers=op).json()
        assert "holds for window=5, debounce=2" in ep["alert_note"] and "debounce=3" in ep["alert_note"]
        assert "recalibrate" in ep["alert_note"] and ep["rule"] is None and ep["risk"] == []
        assert re.search(r'jepa_monitor_calibration_stale\{checkpoint="",task="Square"\} 1\.0',
                         c.get("/metrics", headers=op).text)
        assert c.post("/v1/calibrations", json={"task": "Square"}, headers=ADMIN_H).status_code == 201
        worse = records_for_nmse("bad-2", "Square", rng, [5.0] * 10, held_out=False)
        assert len(post_batch(c, robot, worse).json()["alerts_raised"]) == 1
        metrics = c.get("/metrics", headers=op).text
        assert re.search(r'jepa_monitor_calibration_stale\{checkpoint="",task="Square"\} 0\.0', metrics)


def test_calibration_reports_controls_detection_and_assumptions(client, robot, admin):
    register_task(client, "Square")
    rng = np.random.default_rng(3)
    _calibration_set(client, robot, rng, z_now=True)
    r = client.post("/v1/calibrations", json={"task": "Square", "n_bootstrap": 300, "n_permutation": 300,
                                              "folds": 4}, headers=admin)
    assert r.status_code == 201, r.text
    res = r.json()["result"]
    for name in ("persistence", "residualised"):
        c = res["controls"][name]
        assert c["auroc"] is not None and c["ci"][0] <= c["auroc"] <= c["ci"][1] and c["n"] == 36
    assert res["controls"]["residualised"]["fit"]["decisions"] == 36 * 12
    for kind in ("band", "running"):
        d = res["detection"][kind]
        assert d["folds"] == 4 and d["successes"] + d["failures"] + d["skipped_episodes"] == 36
        if d["true_alerts"]:
            # lead = length (96 env steps) - the env step at which the alert became known
            assert d["detection_step"]["median"] + d["lead_steps"]["median"] == pytest.approx(96)
    assert "exchangeable" in res["assumptions"] and res["alpha"] == 0.1


def test_metrics_export_the_false_alert_target_and_live_rates(client, robot, operator, admin):
    register_task(client, "Square")
    rng = np.random.default_rng(4)
    _calibration_set(client, robot, rng)
    client.post("/v1/calibrations", json={"task": "Square", "alpha": 0.2, "n_bootstrap": 200,
                                          "n_permutation": 200}, headers=admin).raise_for_status()
    post_batch(client, robot, records_for_nmse("live-bad", "Square", rng, [5.0] * 8, held_out=False, success=False))
    post_batch(client, robot, records_for_nmse("live-ok", "Square", rng, [0.1] * 8, held_out=False, success=True))
    text = client.get("/metrics", headers=operator).text
    assert re.search(r'jepa_monitor_calibration_false_alert_target\{checkpoint="",rule="band",task="Square"\} 0\.2',
                     text)
    assert 'jepa_monitor_task_live_alert_rate{task="Square"} 0.5' in text
    assert 'jepa_monitor_task_live_false_alert_rate{task="Square"} 0.0' in text


def test_early_score_uses_the_first_decisions_by_step_whatever_the_arrival_order(client, robot, operator):
    register_task(client, "Square")
    rng = np.random.default_rng(5)
    values = [0.01, 0.012, 0.009, 0.011, 0.0097] + [10.0] * 5
    recs = records_for_nmse("ooo", "Square", rng, values, held_out=True)
    later, earlier = recs[10:], recs[:10]     # steps 40-72 (with their targets) arrive before steps 0-32
    assert post_batch(client, robot, later).status_code == 200
    assert client.get("/v1/episodes/ooo", headers=operator).json()["early_score"] == pytest.approx(10.0, rel=1e-4)
    assert post_batch(client, robot, earlier).status_code == 200
    assert client.get("/v1/episodes/ooo", headers=operator).json()["early_score"] == pytest.approx(0.0100, rel=1e-3)


def test_a_calibration_from_before_episode_rules_raises_nothing_and_says_so(client, robot, operator):
    register_task(client, "Square")
    with client.app.state.sessionmaker() as s:   # the row an earlier version wrote: early-score threshold only
        s.add(CalibrationRow(task="Square", checkpoint=None, active=True, rule="conformal", threshold=0.01,
                             auroc=0.7, result={"auroc": 0.7, "conformal_threshold": 0.01}))
        s.commit()
    rng = np.random.default_rng(6)
    assert post_batch(client, robot, records_for_nmse("old", "Square", rng, [5.0] * 8, held_out=False)).json()[
        "alerts_raised"] == []
    note = client.get("/v1/episodes/old", headers=operator).json()["alert_note"]
    assert "predates episode-level alert rules" in note and "recalibrate" in note
    with client.app.state.sessionmaker() as s:
        assert s.scalar(select(Episode.risk_score).where(Episode.id == "old")) is None


def test_a_calibration_from_before_per_length_promises_raises_nothing_and_says_so(client, robot, operator, admin):
    """A stored rule of the release that merged scarce length bins (no ``promise`` per regime, no
    ``unpromised_lengths``): its merged bins alerted above alpha with nothing said, so it alerts no more, its
    episodes say why and the stale gauge asks for a recalibration."""
    register_task(client, "Square")
    rng = np.random.default_rng(8)
    _calibration_set(client, robot, rng)
    made = client.post("/v1/calibrations", json={"task": "Square", "alpha": 0.2, "n_bootstrap": 200,
                                                 "n_permutation": 200}, headers=admin).json()
    with client.app.state.sessionmaker() as s:   # the same calibration as the earlier release stored it
        row = s.get(CalibrationRow, made["id"])
        old = json.loads(json.dumps(row.result))
        for part in [old["rule"], *old["detector"]["rules"].values()]:
            part.pop("unpromised_lengths")
            part.pop("promise_min")
            for regime in part["regimes"]:
                regime.pop("promise")
        row.result = old
        s.commit()
    client.app.state.ingest.forget_calibrations()
    assert post_batch(client, robot, records_for_nmse("old-rule", "Square", rng, [5.0] * 8, held_out=False)).json()[
        "alerts_raised"] == []
    note = client.get("/v1/episodes/old-rule", headers=operator).json()["alert_note"]
    assert "predates per-length promises" in note and "recalibrate" in note
    assert re.search(r'jepa_monitor_calibration_stale\{checkpoint="",task="Square"\} 1\.0',
                     client.get("/metrics", headers=operator).text)
