"""Named per-decision scores beside the latents: calibrated and alerted on per task and
signal through the real HTTP service, exactly as the offline detectors judge; bad scores refused with a clear
4xx and nothing accepted lost; a policy without a future head sends scores alone; MonitorClient sends them."""
import re

import httpx
import numpy as np
import pytest
from monitor_testkit import ADMIN, DIM, post_batch, records_with_scores, register_task

from monitor_service.signals import CalibratedDetector, DetectorSpec, calibrate_detector
from monitor_service.calibration import LabelledEpisode
from monitor_service.client import MonitorClient
from monitor_service.server import start_server

A = {"X-API-Key": ADMIN}


def two_signal_episode(rng, success, n, drift=0.0):
    """nmse and stac per decision (stac has no first value: no previous chunk), log-normal and correlated; a
    failure drifts up over its second half (both signals); rnd is independent noise."""
    z = rng.normal(size=(3, n))
    ramp = 0 if success else drift * np.clip((np.arange(n) - n / 2) / (n / 2), 0, 1)
    nmse = np.exp(-2.0 + 0.5 * z[0] + ramp)
    stac = np.exp(0.5 * (0.6 * z[0] + 0.8 * z[1]) + ramp)
    stac[0] = np.nan
    return nmse, {"stac": stac, "rnd": np.exp(0.3 * z[2])}


def _as_labelled(name, nmse, scores, success):
    decisions = [{"step": 8 * i, "target_step": 8 * i + 4, "nmse": float(nmse[i]),
                  "scores": {k: float(v[i]) for k, v in scores.items() if np.isfinite(v[i])}}
                 for i in range(len(nmse))]
    return LabelledEpisode(name, success, decisions)


def test_per_signal_calibration_and_alerts_through_the_http_service(tmp_path):
    rng = np.random.default_rng(0)
    calib = [(f"cal-{i}", *two_signal_episode(rng, i % 4 != 0, int(rng.integers(10, 40)), drift=2.5), i % 4 != 0)
             for i in range(120)]
    live = [(f"live-{i}", *two_signal_episode(rng, i % 2 == 0, int(rng.integers(10, 40)), drift=2.5), i % 2 == 0)
            for i in range(40)]
    with start_server(f"sqlite:///{tmp_path / 'm.db'}", admin_key=ADMIN, log_path=tmp_path / "s.log") as server, \
            httpx.Client(base_url=server.url, timeout=120) as http:
        r = http.put("/v1/tasks/Square", json={"latent_dim": DIM, "signals": ["stac", "rnd"]}, headers=A)
        assert r.status_code == 200 and r.json()["signals"] == ["rnd", "stac"]
        robot = {"X-API-Key": http.post("/v1/keys", json={"name": "r", "role": "robot", "robot": "arm1"},
                                        headers=A).json()["key"]}
        op = {"X-API-Key": http.post("/v1/keys", json={"name": "o", "role": "operator"}, headers=A).json()["key"]}
        for name, nmse, scores, success in calib:
            recs = records_with_scores(name, "Square", rng, nmse.tolist(), scores, success=success)
            assert http.post("/v1/batch", json={"records": recs}, headers=robot).status_code == 200
        # the service reads its held-out episodes in id order
        offline = [_as_labelled(n, a, s, ok).signal_episode() for n, a, s, ok in sorted(calib, key=lambda c: c[0])]
        for spec_json, spec in (
                ({"signals": ["stac"]}, DetectorSpec(("stac",))),
                ({"signals": ["nmse", "stac"], "combination": "fiper"},
                 DetectorSpec(("nmse", "stac"), "fiper")),
                ({"signals": ["stac", "rnd", "nmse"]}, DetectorSpec(("stac", "rnd", "nmse"), "bonferroni"))):
            cal = http.post("/v1/calibrations", json={"task": "Square", "alpha": 0.2, "seed": 3, "rule": "band",
                                                      "n_bootstrap": 200, "n_permutation": 200, **spec_json}, headers=A)
            assert cal.status_code == 201, cal.text
            result = cal.json()["result"]
            # the service's detector is the offline one, calibrated on the same episodes
            expected = calibrate_detector(spec, offline, 0.2, seed=3)
            served = CalibratedDetector.from_dict(result["detector"])
            for signal in spec.signals:
                assert served.rules[signal].threshold == pytest.approx(expected.rules[signal].threshold, rel=1e-4)
            assert set(result["signals"]) == {"nmse", "stac", "rnd"}
            assert all(v["rule"] is not None and v["early_auroc"]["auroc"] is not None
                       for v in result["signals"].values())
        # the last calibration (bonferroni over three signals) alerts live exactly as offline
        for name, nmse, scores, success in live:
            for rec in records_with_scores(name, "Square", rng, nmse.tolist(), scores, held_out=False):
                assert http.post("/v1/batch", json={"records": [rec]}, headers=robot).status_code == 200
        alerts = http.get("/v1/alerts", params={"limit": 1000}, headers=op).json()
        first = {}
        for a in sorted(alerts, key=lambda a: a["id"]):
            first.setdefault(a["episode_id"], a)
        alerted = 0
        for name, nmse, scores, success in live:
            judged = served.judge(_as_labelled(name, nmse, scores, success).signal_episode())
            got = first.get(name)
            assert (got is not None) == judged["alerted"], name
            if got is not None:
                alerted += 1
                assert got["step"] == judged["step"] and got["signals"] == ",".join(judged["signals"])
        assert alerted >= 10
        detail = http.get(f"/v1/episodes/{live[1][0]}", headers=op).json()
        assert detail["detector"] == "bonferroni(stac+rnd+nmse) band"
        assert set(detail["signal_risk"]) == {"stac", "rnd", "nmse"}
        assert detail["decisions"][1]["scores"].keys() == {"stac", "rnd"}
        metrics = http.get("/metrics", headers=op).text
        assert re.search(r'jepa_monitor_score_count\{robot="arm1",signal="stac",task="Square"\} [1-9]', metrics)
        assert re.search(r'jepa_monitor_signal_threshold\{checkpoint="",signal="rnd",task="Square"\} [0-9.]+', metrics)
        assert re.search(r'jepa_monitor_signal_alerting\{checkpoint="",signal="stac",task="Square"\} 1\.0', metrics)
        assert re.search(r'jepa_monitor_signal_alerts_total\{signal="[a-z]+",task="Square"\} [1-9]', metrics)


def test_bad_scores_get_a_clear_4xx_and_lose_nothing(client, robot, operator, admin):
    register_task(client, "Square")
    client.put("/v1/tasks/Square", json={"signals": ["stac"]}, headers=admin).raise_for_status()
    rng = np.random.default_rng(1)
    ok = records_with_scores("kept", "Square", rng, [0.1, 0.2], {"stac": np.array([0.3, 0.4])})
    assert post_batch(client, robot, ok).json()["decisions"] == 2

    def refused(record, status, *phrases):
        r = post_batch(client, robot, ok[:1] + [record])   # a resend of an accepted record, then the bad one
        assert r.status_code == status, r.text
        assert all(p in r.json()["detail"] for p in phrases), r.json()["detail"]

    base = {"kind": "decision", "task": "Square", "episode": "kept", "step": 16, "held_out": True}
    refused({**base, "scores": {"rnd": 0.1}}, 422, "records[1]", "has no signal 'rnd'", "PUT /v1/tasks/Square")
    refused({**base, "scores": {"stac": -1.0}}, 422, "non-negative")
    refused({**base, "scores": {"nmse": 0.1}}, 422, "computed by the service")
    refused({**base, "scores": {"stac": "high"}}, 422, "must be a number")
    refused({**base}, 422, "z_hat (with horizon) or scores")
    r = client.post("/v1/decisions", content=b'{"task": "Square", "episode": "kept", "step": 16, "scores": '
                                             b'{"stac": NaN}}', headers={**robot, "Content-Type": "application/json"})
    assert r.status_code == 422 and "score 'stac' is nan" in r.json()["detail"]
    # nothing of the refused requests was written; the accepted episode is intact
    ep = client.get("/v1/episodes/kept", headers=operator).json()
    assert ep["n_decisions"] == 2 and [d["scores"] for d in ep["decisions"]] == [{"stac": 0.3}, {"stac": 0.4}]


def test_a_live_score_of_a_signal_the_calibration_lacks_is_refused(client, robot, admin):
    register_task(client, "Square")
    client.put("/v1/tasks/Square", json={"signals": ["stac", "rnd"]}, headers=admin).raise_for_status()
    rng = np.random.default_rng(2)
    for i in range(30):
        nmse, scores = two_signal_episode(rng, i % 3 != 0, 12, drift=2.0)
        post_batch(client, robot, records_with_scores(f"c{i}", "Square", rng, nmse.tolist(), {"stac": scores["stac"]},
                                                       success=i % 3 != 0)).raise_for_status()
    cal = client.post("/v1/calibrations", json={"task": "Square", "signals": ["stac"], "alpha": 0.2,
                                                "n_bootstrap": 200, "n_permutation": 200}, headers=admin)
    assert cal.status_code == 201, cal.text
    live = {"kind": "decision", "task": "Square", "episode": "lv", "step": 0, "scores": {"rnd": 0.5}}
    r = post_batch(client, robot, [live])
    assert r.status_code == 409 and "calibrated (calibration #1) without signal 'rnd'" in r.json()["detail"]
    assert "held_out: true" in r.json()["detail"]
    assert post_batch(client, robot, [{**live, "held_out": True}]).status_code == 200   # calibration data: fine
    assert post_batch(client, robot, [{**live, "episode": "lv2", "scores": {"stac": 0.5}}]).status_code == 200
    r = client.post("/v1/calibrations", json={"task": "Square", "signals": ["xyz"]}, headers=admin)
    assert r.status_code == 404 and "has no signal 'xyz'" in r.json()["detail"]


def test_a_policy_without_a_future_head_sends_scores_alone(client, robot, operator, admin):
    register_task(client, "MIP")
    client.put("/v1/tasks/MIP", json={"signals": ["stac"]}, headers=admin).raise_for_status()
    rng = np.random.default_rng(3)
    for i in range(40):
        _, scores = two_signal_episode(rng, i % 4 != 0, 12, drift=3.0)
        post_batch(client, robot, records_with_scores(f"m{i}", "MIP", rng, None, {"stac": scores["stac"]},
                                                      success=i % 4 != 0)).raise_for_status()
    cal = client.post("/v1/calibrations", json={"task": "MIP", "signals": ["stac"], "alpha": 0.2,
                                                "n_bootstrap": 200, "n_permutation": 200}, headers=admin)
    assert cal.status_code == 201, cal.text
    assert cal.json()["result"]["ranking_signal"] == "stac" and set(cal.json()["result"]["signals"]) == {"stac"}
    _, scores = two_signal_episode(rng, False, 12, drift=6.0)
    r = post_batch(client, robot, records_with_scores("m-live", "MIP", rng, None, {"stac": scores["stac"]},
                                                      held_out=False))
    assert r.status_code == 200 and len(r.json()["alerts_raised"]) == 1
    ep = client.get("/v1/episodes/m-live", headers=operator).json()
    assert ep["decisions"][0]["horizon"] is None and ep["early_score"] is None and ep["gaps"] == 0


def test_monitor_client_sends_scores(tmp_path):
    with start_server(f"sqlite:///{tmp_path / 'm.db'}", admin_key=ADMIN, log_path=tmp_path / "s.log") as server, \
            httpx.Client(base_url=server.url, timeout=60) as http:
        http.put("/v1/tasks/Square", json={"latent_dim": DIM, "signals": ["stac"]}, headers=A).raise_for_status()
        key = http.post("/v1/keys", json={"name": "r", "role": "robot", "robot": "arm1"}, headers=A).json()["key"]
        rng = np.random.default_rng(4)
        with MonitorClient(server.url, key) as monitor:
            assert monitor.decision("Square", "c", 0, 4, rng.normal(size=DIM), scores={"stac": 0.25})
            assert monitor.decision("Square", "c", 8, None, None, scores={"stac": 0.5})
            with pytest.raises(ValueError, match="finite, non-negative"):
                monitor.decision("Square", "c", 16, None, None, scores={"stac": float("nan")})
            with pytest.raises(ValueError, match="z_hat"):
                monitor.decision("Square", "c", 16, None, None)
            assert monitor.flush(30) and not monitor.stats.rejected
        detail = http.get("/v1/episodes/c", headers=A).json()
        assert [d["scores"] for d in detail["decisions"]] == [{"stac": 0.25}, {"stac": 0.5}]
