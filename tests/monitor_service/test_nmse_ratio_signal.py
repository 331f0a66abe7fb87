"""``nmse_ratio``, the service's second built-in signal: NMSE over the persistence NMSE of the same
decision, derived when both are known (at the target step, like NMSE), the one definition ``jepa-monitor
compare`` uses too; calibrated (HTTP and CLI), combined and alerted on live through the real HTTP service exactly
as the offline detector judges; refused with a clear 4xx when a robot sends it, and a calibration without z_now
names the fix; its false-alert promise holds on fresh successes within the binomial bound."""
import re
import sqlite3
import time

import httpx
import numpy as np
import pytest
from monitor_testkit import ADMIN, DIM, make_settings, post_batch, records_for_nmse, register_task
from scipy.stats import binomtest

from monitor_service import rules, scoring
from monitor_service.offline import compare
from monitor_service.signals import CalibratedDetector, DetectorSpec, calibrate_detector
from monitor_service.calibration import LabelledEpisode
from monitor_service.cli import main as monitor_main
from monitor_service.ingest.sql import Sql, load_episode
from monitor_service.server import start_server

A = {"X-API-Key": ADMIN}


def test_nmse_ratio_is_the_reference_formula_on_fixed_inputs():
    # d_NMSE by hand: z = (1, -1) has rms 1; z_hat = (1.5, -1) misses by 0.5 in one of 2 dims: 0.25 / 2 = 0.125;
    # the persistence prediction z_now = (0, 0) misses by 1 in both: 2 / 2 = 1.0; so the ratio is 0.125
    z, z_hat, z_now = np.array([1.0, -1.0]), np.array([1.5, -1.0]), np.array([0.0, 0.0])
    assert scoring.nmse(z_hat, z) == 0.125 and scoring.nmse(z_now, z) == 1.0
    assert scoring.nmse_ratio_or_none(scoring.nmse(z_hat, z), scoring.nmse(z_now, z)) == 0.125
    nmse = [0.3, 0.2, 0.0, 0.5, 0.4, np.nan, 1e-3]
    pers = [0.6, 0.0, 0.1, 1e-12, 2e-12, 0.5, 1e-300]
    want = [0.5, np.nan, 0.0, np.nan, 0.2e12, np.nan, np.nan]   # <= the floor (or 1e-300 / inf): no value
    np.testing.assert_allclose(scoring.nmse_ratio(nmse, pers), want, rtol=1e-15)
    assert scoring.PERSISTENCE_FLOOR == rules.LOG_FLOOR
    assert scoring.nmse_ratio_or_none(None, 0.5) is None and scoring.nmse_ratio_or_none(0.3, None) is None
    assert scoring.nmse_ratio_or_none(0.3, 0.0) is None and scoring.nmse_ratio_or_none(0.3, 0.6) == 0.5
    # the offline compare and the service's calibration read the same values from the same decisions
    decisions = [{"step": 8 * i, "target_step": 8 * i + 4, "nmse": n, "nmse_persistence": p, "scores": {"stac": 1.0}}
                 for i, (n, p) in enumerate(zip(nmse, pers)) if n == n]
    offline = compare.episode_of({"seed": 1, "success": True, "length": 60, "decisions": decisions})
    served = LabelledEpisode("e", True, decisions).signal_episode()
    np.testing.assert_array_equal(offline.values["nmse_ratio"], served.scores["nmse_ratio"])
    np.testing.assert_array_equal(served.series("nmse_ratio").known_at, [4, 20, 36])   # the target steps
    assert LabelledEpisode("e", True, decisions).early("nmse_ratio", 1) == 0.5
    assert LabelledEpisode("e", True, decisions).early("nmse_ratio", 2) is None   # the frozen second decision
    assert "nmse_ratio" not in LabelledEpisode("e", True, [{**d, "nmse_persistence": None}
                                                          for d in decisions]).signal_episode().scores


def ratio_episode(rng, success, n, drift=3.0):
    """(nmse, persistence) per decision: the scene's change (persistence NMSE) varies widely, our error per unit
    of it (the ratio) is log-normal, and a failure's ratio drifts up over its second half."""
    pers = np.exp(rng.normal(-3.0, 1.0, n))
    ramp = 0 if success else drift * np.clip((np.arange(n) - n / 2) / (n / 2), 0, 1)
    return np.exp(rng.normal(0.0, 0.3, n) + ramp) * pers, pers


def labelled(name, nmse, pers, success):
    return LabelledEpisode(name, success, [{"step": 8 * i, "target_step": 8 * i + 4, "nmse": float(nmse[i]),
                                            "nmse_persistence": float(pers[i])} for i in range(len(nmse))])


def test_nmse_ratio_calibrates_and_alerts_through_the_http_service_and_the_cli(tmp_path, capsys):
    rng = np.random.default_rng(38)
    calib = [(f"cal-{i:02d}", *ratio_episode(rng, i % 4 != 0, 12), i % 4 != 0) for i in range(40)]
    url = f"sqlite:///{tmp_path / 'm.db'}"
    with start_server(url, admin_key=ADMIN, log_path=tmp_path / "s.log") as server, \
            httpx.Client(base_url=server.url, timeout=120) as http:
        assert http.put("/v1/tasks/Ratio", json={"latent_dim": DIM}, headers=A).status_code == 200
        robot = {"X-API-Key": http.post("/v1/keys", json={"name": "r", "role": "robot", "robot": "arm1"},
                                        headers=A).json()["key"]}
        for name, nmse, pers, success in calib:
            recs = records_for_nmse(name, "Ratio", rng, nmse.tolist(), success=success, persistence=pers.tolist())
            assert http.post("/v1/batch", json={"records": recs}, headers=robot).status_code == 200
        offline = [labelled(*c).signal_episode() for c in calib]   # ids sort as the service reads them
        body = {"task": "Ratio", "alpha": 0.2, "seed": 3, "rule": "band", "n_bootstrap": 200, "n_permutation": 200}
        for extra in ({"signals": ["nmse_ratio", "nmse"], "combination": "fiper"},
                      {"signals": ["nmse", "nmse_ratio"], "combination": "bonferroni"}):
            r = http.post("/v1/calibrations", json={**body, **extra}, headers=A)
            assert r.status_code == 201, r.text
            assert r.json()["result"]["detector"]["spec"]["signals"] == extra["signals"]
        result = r.json()["result"]
        assert result["signals"]["nmse_ratio"]["rule"] is not None
        # the ratio ranks this task's failures; NMSE, swamped by the scene's own change, ranks them worse
        assert result["signals"]["nmse_ratio"]["early_auroc"]["auroc"] > result["signals"]["nmse"]["early_auroc"][
            "auroc"]
        # the active calibration made by the CLI, alerting on nmse_ratio alone, is the offline one
        assert monitor_main(["--database-url", url, "calibrate", "--task", "Ratio", "--signals", "nmse_ratio",
                             "--alpha", "0.2", "--seed", "3", "--rule", "band", "--n-bootstrap", "200",
                             "--n-permutation", "200"]) == 0
        out = capsys.readouterr().out
        assert "detector single of nmse_ratio" in out and "signal nmse_ratio: early-score AUROC 0." in out
        served = CalibratedDetector.from_dict(
            http.get("/v1/calibrations", params={"task": "Ratio", "active": True}, headers=A).json()[0]["result"][
                "detector"])
        expected = calibrate_detector(DetectorSpec(("nmse_ratio",)), offline, 0.2, seed=3)
        assert served.rules["nmse_ratio"].threshold == pytest.approx(expected.rules["nmse_ratio"].threshold, rel=1e-4)
        time.sleep(detectors_ttl())   # the server sees the other process's calibration
        # live: a failure whose ratio climbs from its 4th decision, a success at the ratio's median (one frozen
        # decision: no ratio there), and a failure that sent no z_now (the detector cannot see it; its note says so)
        fail_pers = np.exp(rng.normal(-3.0, 1.0, 12))
        fail_nmse = fail_pers * np.exp(np.where(np.arange(12) >= 3, 3.0, 0.0))
        ok_pers = np.exp(rng.normal(-3.0, 1.0, 12))
        ok_pers[5] = 0.0
        ok_nmse = np.where(ok_pers > 0, ok_pers, 0.05)
        live = [("live-fail", fail_nmse, fail_pers, False), ("live-ok", ok_nmse, ok_pers, True)]
        for name, nmse, pers, _ in live:
            for rec in records_for_nmse(name, "Ratio", rng, nmse.tolist(), held_out=False, persistence=pers.tolist()):
                assert http.post("/v1/batch", json={"records": [rec]}, headers=robot).status_code == 200
        for rec in records_for_nmse("live-blind", "Ratio", rng, (fail_nmse * 10).tolist(), held_out=False):
            assert http.post("/v1/batch", json={"records": [rec]}, headers=robot).status_code == 200
        alerts = {a["episode_id"]: a for a in http.get("/v1/alerts", headers=A).json()}
        assert set(alerts) == {"live-fail"}
        judged = served.judge(labelled(*live[0]).signal_episode())
        assert judged["alerted"] and not served.judge(labelled(*live[1]).signal_episode())["alerted"]
        assert alerts["live-fail"]["signals"] == "nmse_ratio" and alerts["live-fail"]["step"] == judged["step"]
        detail = http.get("/v1/episodes/live-fail", headers=A).json()
        assert detail["detector"] == "nmse_ratio band" and set(detail["signal_risk"]) == {"nmse_ratio"}
        assert [d["nmse_ratio"] for d in detail["decisions"]] == pytest.approx(fail_nmse / fail_pers, rel=1e-4)
        ok = http.get("/v1/episodes/live-ok", headers=A).json()
        assert ok["decisions"][5]["nmse_persistence"] == 0.0 and ok["decisions"][5]["nmse_ratio"] is None
        assert len(ok["signal_risk"]["nmse_ratio"]) == 11
        blind = http.get("/v1/episodes/live-blind", headers=A).json()
        assert "sent no z_now" in blind["alert_note"] and blind["decisions"][0]["nmse_ratio"] is None
        metrics = http.get("/metrics", headers=A).text
        assert re.search(r'jepa_monitor_score_count\{robot="arm1",signal="nmse_ratio",task="Ratio"\} [1-9]', metrics)
        assert re.search(r'jepa_monitor_signal_threshold\{checkpoint="",signal="nmse_ratio",task="Ratio"\} [0-9.]+',
                         metrics)
        assert re.search(r'jepa_monitor_signal_alerting\{checkpoint="",signal="nmse_ratio",task="Ratio"\} 1\.0',
                         metrics)
        assert re.search(r'jepa_monitor_signal_alerts_total\{signal="nmse_ratio",task="Ratio"\} 1\.0', metrics)
    # another process resumes an episode from its stored rows: the ratio is derived again (it is not stored)
    with sqlite3.connect(tmp_path / "m.db") as conn:
        loaded = {e: load_episode(Sql("sqlite"), conn.cursor(), e).values("nmse_ratio")
                  for e in ("live-fail", "live-ok")}
    assert [s for s, _ in loaded["live-fail"]] == list(range(0, 96, 8))
    assert [v for _, v in loaded["live-fail"]] == pytest.approx(fail_nmse / fail_pers, rel=1e-4)
    assert [s for s, _ in loaded["live-ok"]] == [s for s in range(0, 96, 8) if s != 40]   # the frozen decision


def detectors_ttl():
    from monitor_service.ingest.alerting import CALIBRATION_TTL_S
    return CALIBRATION_TTL_S + 0.2


def test_a_robot_cannot_send_the_services_signals_and_calibrating_without_z_now_names_the_fix(
        client, robot, admin, tmp_path, capsys):
    register_task(client, "Square")
    rng = np.random.default_rng(5)
    for i in range(12):   # latents without z_now: NMSE only
        nmse, _ = ratio_episode(rng, i % 3 != 0, 8)
        post_batch(client, robot, records_for_nmse(f"e{i}", "Square", rng, nmse.tolist(),
                                                   success=i % 3 != 0)).raise_for_status()
    base = {"kind": "decision", "task": "Square", "episode": "e99", "step": 0, "horizon": 4,
            "z_hat": [0.0] * DIM, "held_out": True}
    for name in ("nmse_ratio", "nmse"):
        r = post_batch(client, robot, [{**base, "scores": {name: 0.1}}])
        assert r.status_code == 422 and f"score {name!r} is computed by the service" in r.json()["detail"]
        assert ("z_now" in r.json()["detail"]) == (name == "nmse_ratio")
    r = client.put("/v1/tasks/Square", json={"signals": ["nmse_ratio"]}, headers=admin)
    assert r.status_code == 422 and "nmse_ratio is the service's own signal" in r.json()["detail"]
    r = client.post("/v1/calibrations", json={"task": "Square", "signals": ["nmse_ratio"], "n_bootstrap": 100,
                                              "n_permutation": 100}, headers=admin)
    assert r.status_code == 409, r.text
    assert "no held-out episode has an nmse_ratio" in r.json()["detail"] and "send z_now" in r.json()["detail"]
    url = ["--database-url", make_settings(tmp_path).database_url]
    assert monitor_main(url + ["calibrate", "--task", "Square", "--signals", "nmse_ratio"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jepa-monitor: error: no held-out episode has an nmse_ratio") and "send z_now" in err
    assert monitor_main(url + ["tasks", "add", "Square", "--signals", "nmse_ratio"]) == 2
    assert "nmse_ratio is the service's own signal" in capsys.readouterr().err
    # nothing refused was written, and a task's calibration on NMSE is unchanged by the new signal
    assert client.get("/v1/episodes/e99", headers=admin).status_code == 404
    r = client.post("/v1/calibrations", json={"task": "Square", "alpha": 0.3, "n_bootstrap": 100,
                                              "n_permutation": 100}, headers=admin)
    assert r.status_code == 201, r.text
    assert set(r.json()["result"]["signals"]) == {"nmse"}


@pytest.mark.parametrize("alpha", [0.2])
def test_nmse_ratio_keeps_the_false_alert_promise_on_fresh_successes(alpha):
    """Independent (calibration set, fresh success) pairs, the ratio derived from (nmse, persistence) as the
    service derives it (frozen decisions left out), lengths 5-40: alerts ~ Binomial(PAIRS, p <= alpha)."""
    pairs, alerts = 200, 0
    spec = DetectorSpec(("nmse_ratio",), params=rules.RuleParams("band"))

    def success(rng, i):
        nmse, pers = ratio_episode(rng, True, int(rng.integers(5, 41)))
        pers[rng.random(pers.size) < 0.05] = 0.0   # frozen scenes: no ratio at those decisions
        return labelled(f"s{i}", nmse, pers, True).signal_episode()

    for i in range(pairs):
        rng = np.random.default_rng([38, 7, i])
        detector = calibrate_detector(spec, [success(rng, j) for j in range(40)], alpha, seed=i)
        alerts += detector.judge(success(rng, -1))["alerted"]
    assert binomtest(alerts, pairs, alpha, alternative="greater").pvalue > 1e-3, alerts
    assert alerts >= 5, alerts   # the rule does fire: the promise is not met by never alerting
