"""The HTTP API in-process: ingestion, scoring, idempotency, auth, bad input, calibration, alerts, report."""
import json
import re

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from monitor_service import scoring
from monitor_service.app import create_app
from monitor_service.db import Episode, IdempotencyKey, read_decisions
from monitor_service.encoding import MSGPACK_CONTENT_TYPE, pack
from monitor_service.rules import alert_statistic, running_statistic

from monitor_testkit import DIM, episode_records, make_settings, new_key, post_batch, register_task


def _count(client, model):
    with client.app.state.sessionmaker() as s:
        return s.scalar(select(func.count()).select_from(model))


def _decisions(client) -> int:
    """Decisions stored, over every episode (the decision log folded)."""
    with client.app.state.sessionmaker() as s:
        return sum(map(len, read_decisions(s, list(s.scalars(select(Episode.id)))).values()))


def _alerts_total(metrics: str) -> float:
    m = re.search(r'^jepa_monitor_alerts_total\{robot="arm1",task="Square"\} ([0-9.]+)$', metrics, re.M)
    return float(m.group(1)) if m else 0.0


def test_health_and_readiness(client):
    assert client.get("/healthz").json()["status"] == "ok"
    r = client.get("/readyz")
    assert r.status_code == 200 and r.json()["detail"] == "schema 0006"
    paths = client.get("/openapi.json").json()["paths"]
    assert "application/x-msgpack" in paths["/v1/batch"]["post"]["requestBody"]["content"]


def test_decision_scoring_matches_paper_nmse_and_early_score(client, robot, operator):
    register_task(client, "Square")
    rng = np.random.default_rng(0)
    recs, pairs = episode_records("ep-1", "Square", rng, noise=0.5, n_steps=7)
    r = post_batch(client, robot, recs)
    assert r.status_code == 200, r.text
    assert r.json() == {"accepted": 14, "decisions": 7, "targets": 7, "outcomes": 0, "scored": 7, "alerts_raised": [],
                        "alert_state": {"ep-1": None}, "beyond_calibration": []}
    ep = client.get("/v1/episodes/ep-1", headers=operator).json()
    expected = [scoring.nmse(zh, z) for zh, z in pairs]
    # d_NMSE(z_hat, z) = ||(z_hat - z) / max(rms(z), 1e-6)||^2 / d_z, written out independently:
    zh, z = (p.astype(np.float64) for p in pairs[0])
    assert expected[0] == pytest.approx(np.sum(((zh - z) / np.sqrt(np.mean(z**2))) ** 2) / DIM)
    assert [d["nmse"] for d in ep["decisions"]] == pytest.approx(expected)
    assert ep["early_score"] == pytest.approx(np.median(expected[:5]))
    assert ep["running_score"] == pytest.approx(np.median(expected[-5:]))
    assert ep["robot"] == "arm1" and ep["live"] is True


def test_target_before_decision_and_missing_target_rules(client, robot, operator):
    register_task(client, "Square")
    rng = np.random.default_rng(1)
    z = rng.normal(size=DIM).tolist()
    first = {"kind": "decision", "task": "Square", "episode": "e", "step": 0, "horizon": 3, "z_hat": z}
    target = {"kind": "target", "episode": "e", "step": 3, "z": z}
    assert post_batch(client, robot, [first, target]).json()["scored"] == 1
    # Decisions 1..5: targets for 1, 2, 4, 5 but not 3 -> the early score needs all first five: none.
    recs = [{"kind": "decision", "task": "Square", "episode": "e", "step": t, "horizon": 3, "z_hat": z}
            for t in range(1, 6)]
    recs += [{"kind": "target", "episode": "e", "step": t + 3, "z": z} for t in (1, 2, 4, 5)]
    assert post_batch(client, robot, recs).status_code == 200
    assert client.get("/v1/episodes/e", headers=operator).json()["early_score"] is None
    # The realized latent of step 6 arrives late: decision 3 is scored, the early score appears (all zero error).
    assert post_batch(client, robot, [{"kind": "target", "episode": "e", "step": 6, "z": z}]).json()["scored"] == 1
    assert client.get("/v1/episodes/e", headers=operator).json()["early_score"] == 0.0


def test_binary_and_json_encodings_store_identical_values(client, robot, operator):
    register_task(client, "Square")
    z_hat = np.random.default_rng(2).normal(size=DIM).astype(np.float32)
    z = (z_hat * 1.1).astype(np.float32)
    body = pack({"records": [
        {"kind": "decision", "task": "Square", "episode": "bin", "step": 0, "horizon": 1, "z_hat": z_hat},
        {"kind": "target", "episode": "bin", "step": 1, "z": z},
    ]})
    r = client.post("/v1/batch", content=body, headers={**robot, "Content-Type": MSGPACK_CONTENT_TYPE})
    assert r.status_code == 200, r.text
    post_batch(client, robot, [
        {"kind": "decision", "task": "Square", "episode": "json", "step": 0, "horizon": 1, "z_hat": z_hat.tolist()},
        {"kind": "target", "episode": "json", "step": 1, "z": z.tolist()},
    ])
    a = client.get("/v1/episodes/bin", headers=operator).json()["decisions"][0]["nmse"]
    b = client.get("/v1/episodes/json", headers=operator).json()["decisions"][0]["nmse"]
    assert a == b == pytest.approx(scoring.nmse(z_hat, z))


def test_single_endpoints(client, robot):
    register_task(client, "Square")
    z = [0.5] * DIM
    decision = {"task": "Square", "episode": "s", "step": 0, "horizon": 1, "z_hat": z}
    assert client.post("/v1/decisions", json=decision, headers=robot).status_code == 200
    assert client.post("/v1/targets", json={"episode": "s", "step": 1, "z": z}, headers=robot).json()["scored"] == 1
    assert client.post("/v1/outcomes", json={"episode": "s", "success": True}, headers=robot).json()["outcomes"] == 1


def test_idempotent_retry_never_double_counts(client, robot):
    register_task(client, "Square")
    recs, _ = episode_records("idem", "Square", np.random.default_rng(3), 0.3, n_steps=3)
    first = post_batch(client, robot, recs, key="k-1")
    again = post_batch(client, robot, recs, key="k-1")
    assert first.status_code == again.status_code == 200
    assert again.headers["Idempotent-Replayed"] == "true" and again.json() == first.json()
    assert _decisions(client) == 3 and _count(client, IdempotencyKey) == 1
    other = post_batch(client, robot, recs[:1], key="k-1")
    assert other.status_code == 409 and "different body" in other.json()["detail"]
    # Without a key, an identical record is recognised and not stored twice; a different one is a conflict.
    assert post_batch(client, robot, recs[:2]).json()["decisions"] == 0
    changed = dict(recs[0], z_hat=[9.0] * DIM)
    r = post_batch(client, robot, [changed])
    assert r.status_code == 409 and "different decision at step 0" in r.json()["detail"]
    assert _decisions(client) == 3


def test_auth_roles_and_refusals(client, robot, operator, admin):
    register_task(client, "Square")
    dec = {"task": "Square", "episode": "a", "step": 0, "horizon": 1, "z_hat": [1.0] * DIM}
    assert client.post("/v1/decisions", json=dec).status_code == 401
    assert client.get("/v1/episodes").status_code == 401
    assert client.get("/metrics").status_code == 401
    assert client.get("/v1/episodes", headers={"X-API-Key": "nope"}).status_code == 401
    r = client.get("/v1/episodes", headers=robot)
    assert r.status_code == 403 and "operator" in r.json()["detail"]
    assert client.post("/v1/calibrations", json={"task": "Square"}, headers=operator).status_code == 403
    assert client.post("/v1/keys", json={"name": "x", "role": "admin"}, headers=operator).status_code == 403
    # A robot key writes only for its own robot and its own episodes.
    r = client.post("/v1/decisions", json={**dec, "robot": "arm2"}, headers=robot)
    assert r.status_code == 403 and "arm1" in r.json()["detail"]
    arm2 = new_key(client, "arm2-key", "robot", "arm2")
    assert client.post("/v1/decisions", json=dec, headers=arm2).status_code == 200
    r = client.post("/v1/targets", json={"episode": "a", "step": 1, "z": [1.0] * DIM}, headers=robot)
    assert r.status_code == 403 and "belongs to robot 'arm2'" in r.json()["detail"]
    # Revoked keys stop working; bearer tokens work like X-API-Key.
    keys = client.get("/v1/keys", headers=admin).json()
    arm2_id = next(k["id"] for k in keys if k["name"] == "arm2-key")
    token = arm2["X-API-Key"]
    assert client.post("/v1/outcomes", json={"episode": "a", "success": True},
                       headers={"Authorization": f"Bearer {token}"}).status_code == 200
    assert client.delete(f"/v1/keys/{arm2_id}", headers=admin).status_code == 200
    r = client.delete("/v1/keys/999", headers=admin)
    assert r.status_code == 404 and r.json()["detail"] == "API key id 999 does not exist; list keys with GET /v1/keys"
    assert client.post("/v1/targets", json={"episode": "a", "step": 1, "z": [1.0] * DIM},
                       headers=arm2).status_code == 401
    r = client.post("/v1/keys", json={"name": "r", "role": "robot"}, headers=admin)
    assert r.status_code == 422 and "body.robot.robot: Field required" in r.json()["detail"]
    r = client.post("/v1/keys", json={"name": "o", "role": "operator", "robot": "arm1"}, headers=admin)
    assert r.status_code == 422 and "body.operator.robot" in r.json()["detail"]
    assert client.post("/v1/keys", json={"name": "arm1-key", "role": "admin"}, headers=admin).status_code == 409


def test_only_robot_keys_ingest(client, robot, operator, admin):
    """An operator reads and acknowledges; an admin configures. Neither may write calibration data."""
    register_task(client, "Square")
    records = {"/v1/decisions": {"task": "Square", "episode": "e", "step": 0, "horizon": 1, "z_hat": [1.0] * DIM},
               "/v1/targets": {"episode": "e", "step": 1, "z": [1.0] * DIM},
               "/v1/outcomes": {"episode": "e", "success": True},
               "/v1/batch": {"records": [{"kind": "outcome", "episode": "e", "success": True}]}}
    for path, body in records.items():
        for key in (operator, admin):
            r = client.post(path, json=body, headers=key)
            assert r.status_code == 403 and "robot keys only" in r.json()["detail"], (path, r.text)
    assert _count(client, Episode) == 0
    assert client.post("/v1/decisions", json=records["/v1/decisions"], headers=robot).status_code == 200


@pytest.mark.parametrize("method, path, body, field", [
    ("GET", f"/v1/calibrations/{2**63}", None, "calibration_id"),
    ("GET", f"/v1/calibrations/{2**31}", None, "calibration_id"),
    ("POST", f"/v1/alerts/{2**64}/ack", None, "alert_id"),
    ("DELETE", f"/v1/keys/{10**30}", None, "key_id"),
    ("POST", "/v1/decisions", b'{"task":"Square","episode":"b","step":9223372036854775808,"horizon":1,'
                              b'"z_hat":[1]}', "step"),
    ("POST", "/v1/decisions", b'{"task":"Square","episode":"b","step":0,"horizon":99999999999,"z_hat":[1]}', "horizon"),
    ("POST", "/v1/decisions", b'{"task":"Square","episode":"b","step":0,"horizon":1,"z_hat":[1,' + b"9" * 400 + b']}',
     "index 1"),
    ("POST", "/v1/batch", b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
    ("POST", "/v1/calibrations", b'{"task":"Square","seed":-1}', "seed"),
    ("POST", "/v1/calibrations", b'{"task":"Square","alpha":1e-300}', "alpha"),
    ("PUT", "/v1/tasks/Square", b'{"latent_dim":' + b"9" * 40 + b'}', "latent_dim"),
    ("GET", "/v1/episodes?limit=99999999999999999999999", None, "limit"),
], ids=["id-2^63", "id-2^31", "alert-2^64", "key-1e30", "step-2^63", "horizon", "latent-400-digits",
        "nested-100000", "seed", "alpha", "latent_dim", "limit"])
def test_out_of_range_input_is_a_4xx_naming_the_field(client, robot, admin, method, path, body, field):
    register_task(client, "Square")
    key = robot if path in ("/v1/decisions", "/v1/batch") else admin
    r = client.request(method, path, content=body, headers={**key, "Content-Type": "application/json"})
    assert 400 <= r.status_code < 500, r.text
    assert field in r.json()["detail"], r.text
    assert _decisions(client) == 0


@pytest.mark.parametrize(
    "body, status, message",
    [
        (b'{"task":"Square","episode":"b","step":0,"horizon":1,"z_hat":[NaN,0,0]}', 422, "NaN or inf at index 0"),
        (b'{"task":"Square","episode":"b","step":0,"horizon":1,"z_hat":[Infinity]}', 422, "NaN or inf"),
        (b'{"task":"Square","episode":"b","step":0,"horizon":1,"z_hat":[1,2,3]}', 422,
         "3 dimensions but task 'Square' uses latents of 16"),
        (b'{"task":"Square","episode":"b","step":0,"horizon":1,"z_hat":[[1,2],[3,4]]}', 422,
         "latent must be a list of numbers"),
        (b'{"task":"Square","episode":"b","step":0,"horizon":1,"z_hat":[]}', 422, "non-empty"),
        (b'{"task":"Cube","episode":"b","step":0,"horizon":1,"z_hat":[1]}', 404, "task 'Cube' is not registered"),
        (b'{"task":"Square","episode":"b","step":-1,"horizon":1,"z_hat":[1]}', 422, "step"),
        (b'{"task":"Square","episode":"b","step":0,"horizon":0,"z_hat":[1]}', 422, "horizon"),
        (b'{"task":"Square","episode":"b","step":0,"horizon":1,"z_hat":[1],"extra":1}', 422, "extra"),
        (b'{"task":"Square","episode":"b", "step":0', 400, "malformed JSON"),
        (b'[1,2]', 422, ""),
    ],
)
def test_bad_decisions_are_refused_and_change_nothing(client, robot, body, status, message):
    register_task(client, "Square")
    r = client.post("/v1/decisions", content=body, headers={**robot, "Content-Type": "application/json"})
    assert r.status_code == status, r.text
    assert message in r.json()["detail"]
    assert _decisions(client) == 0 and _count(client, Episode) == 0


def test_bad_batch_rolls_back_everything_and_names_the_record(client, robot, operator):
    register_task(client, "Square")
    good, _ = episode_records("g", "Square", np.random.default_rng(4), 0.2, n_steps=2)
    assert post_batch(client, robot, good).status_code == 200
    before = client.get("/v1/episodes/g", headers=operator).json()
    more, _ = episode_records("g2", "Square", np.random.default_rng(5), 0.2, n_steps=2)
    bad = more + [{"kind": "target", "episode": "ghost", "step": 1, "z": [0.0] * DIM}]
    r = post_batch(client, robot, bad)
    assert r.status_code == 404 and r.json()["detail"].startswith("records[4] (target): episode 'ghost' is unknown")
    assert client.get("/v1/episodes/g2", headers=operator).status_code == 404
    assert client.get("/v1/episodes/g", headers=operator).json() == before
    mismatch = [{"kind": "target", "episode": "g", "step": 9, "z": [0.0] * 5}]
    assert "5 dimensions" in post_batch(client, robot, mismatch).json()["detail"]
    r = client.post("/v1/outcomes", json={"episode": "nope", "success": False}, headers=robot)
    assert r.status_code == 404
    assert client.post("/v1/outcomes", json={"episode": "g", "success": False}, headers=robot).status_code == 200
    r = client.post("/v1/outcomes", json={"episode": "g", "success": True}, headers=robot)
    assert r.status_code == 409 and "outcomes are final" in r.json()["detail"]
    dec = {"kind": "decision", "task": "Square", "episode": "g", "step": 50, "horizon": 1, "z_hat": [0.0] * DIM}
    assert "has ended" in post_batch(client, robot, [dec]).json()["detail"]
    bad_bin = client.post("/v1/batch", content=b"\xc1\xc1", headers={**robot, "Content-Type": MSGPACK_CONTENT_TYPE})
    assert bad_bin.status_code == 400 and "malformed msgpack" in bad_bin.json()["detail"]
    cut = {"dtype": "<f4", "shape": [16], "data": b"\0" * 8}
    short = pack({"records": [{"kind": "target", "episode": "g", "step": 3, "z": cut}]})
    r = client.post("/v1/batch", content=short, headers={**robot, "Content-Type": MSGPACK_CONTENT_TYPE})
    assert r.status_code == 400 and "needs 64" in r.json()["detail"]
    r = client.post("/v1/batch", content=b"x", headers={**robot, "Content-Type": "text/plain"})
    assert r.status_code == 400 and "not supported" in r.json()["detail"]


def test_oversized_payload_gets_413(tmp_path):
    settings = make_settings(tmp_path, max_body_bytes=2048)
    with TestClient(create_app(settings)) as c:
        register_task(c, "Square")
        robot = new_key(c, "r", "robot", "arm1")
        big = {"task": "Square", "episode": "big", "step": 0, "horizon": 1, "z_hat": [0.123456789] * 400}
        r = c.post("/v1/decisions", json=big, headers=robot)
        assert r.status_code == 413 and "2048-byte limit" in r.json()["detail"]
        # Chunked upload without Content-Length is cut off while streaming.
        body = json.dumps(big).encode()
        r = c.post("/v1/decisions", content=iter([body[:1000], body[1000:]]),
                   headers={**robot, "Content-Type": "application/json"})
        assert r.status_code == 413
        with c.app.state.sessionmaker() as s:
            assert s.scalar(select(func.count()).select_from(Episode)) == 0


def _ingest_calibration_set(client, robot, task, rng, n_success, n_failure, s_noise, f_noise,
                            groups=("seed0", "seed1")):
    for i in range(n_success + n_failure):
        fail = i >= n_success
        recs, _ = episode_records(f"{task}-{i}", task, rng, f_noise if fail else s_noise, n_steps=6,
                                  success=not fail, group=groups[i % len(groups)])
        assert post_batch(client, robot, recs).status_code == 200


def test_calibration_report_and_alerts_end_to_end(client, robot, operator, admin):
    register_task(client, "Square")
    rng = np.random.default_rng(7)
    # Without a calibration, episodes raise no alert and say why.
    recs, _ = episode_records("live-0", "Square", rng, 1.0, n_steps=8, held_out=False)
    post_batch(client, robot, recs)
    ep = client.get("/v1/episodes/live-0", headers=operator).json()
    assert ep["open_alert_id"] is None and "no active calibration" in ep["alert_note"]
    assert client.get("/v1/alerts", headers=operator).json() == []

    _ingest_calibration_set(client, robot, "Square", rng, 30, 12, 0.3, 0.6)
    r = client.post("/v1/calibrations", json={"task": "Square", "alpha": 0.1, "seed": 1, "rule": "running"},
                    headers=admin)
    assert r.status_code == 201, r.text
    cal = r.json()
    res = cal["result"]
    assert res["n_success"] == 30 and res["n_failure"] == 12 and res["skipped_episodes"] == 0
    assert res["auroc"] > 0.9 and res["auroc_ci_low"] <= res["auroc"] <= res["auroc_ci_high"]
    assert res["held_out_method"] == "leave-one-group-out over 2 groups"
    # Every episode has 6 decisions: one length regime of all 30 successes, and the flat threshold is the
    # ceil(31 * 0.9) = 28th smallest of their alert statistics (per episode the largest min over 2 consecutive
    # running medians, window 5, of its NMSE), recomputed here from the stored rows.
    with client.app.state.sessionmaker() as s:
        ids = s.scalars(select(Episode.id).where(Episode.held_out.is_(True), Episode.success.is_(True))).all()
        stat = sorted(alert_statistic(running_statistic(np.array([d["nmse"] for d in read_decisions(s, [i])[i]]), 5),
                                      2) for i in ids)
    assert cal["threshold"] == pytest.approx(stat[27]) and cal["rule"] == "running"
    assert res["rule"]["regimes"] == [{"lo": 1, "hi": 6, "n": 30, "rank": 28, "level": pytest.approx(np.log(stat[27])),
                                         "promise": True}]
    assert res["rule"]["n_conformal"] == 30 and res["rule"]["calibrated_decisions"] == 6
    for kind in ("running", "band"):   # cross-fitted detection figures of both rules
        d = res["detection"][kind]
        assert d["successes"] + d["failures"] + d["skipped_episodes"] == 42
        assert d["false_alert_ci"][0] <= d["false_alert_rate"] <= d["false_alert_ci"][1]
    assert res["controls"]["persistence"]["auroc"] is None and "z_now" in res["controls"]["persistence"]["reason"]

    # A bad live episode now raises exactly one alert (debounce 2, hysteresis), visible everywhere.
    alerts_before = _alerts_total(client.get("/metrics", headers=operator).text)
    recs, _ = episode_records("live-bad", "Square", rng, 1.5, n_steps=10, held_out=False)
    post_batch(client, robot, recs)
    ep = client.get("/v1/episodes/live-bad", headers=operator).json()
    assert ep["open_alert_id"] is not None and "alerting with nmse" in ep["alert_note"]
    alerts = client.get("/v1/alerts?state=open", headers=operator).json()
    assert [a["episode_id"] for a in alerts] == ["live-bad"]
    assert alerts[0]["score"] > alerts[0]["threshold"]
    detail = client.get("/v1/episodes/live-bad", headers=operator).json()
    raised_at = next(p for p in detail["risk"] if p["step"] == alerts[0]["step"])
    assert alerts[0]["threshold"] == pytest.approx(raised_at["threshold"])
    assert raised_at["threshold"] <= cal["threshold"] == pytest.approx(detail["threshold"])
    # Operator acknowledges; the DB keeps who and when.
    ack = client.post(f"/v1/alerts/{alerts[0]['id']}/ack", json={"note": "taking over"}, headers=operator).json()
    assert ack["acknowledged_by"] == "op-key" and ack["note"] == "taking over"
    assert client.post("/v1/alerts/999/ack", headers=operator).status_code == 404

    rep = client.get("/v1/report", headers=operator).json()
    assert [t["task"] for t in rep["tasks"]] == ["Square"] and "WARNING" in rep["pooled"]["warning"]
    metrics = client.get("/metrics", headers=operator).text
    assert 'jepa_monitor_task_auroc{task="Square"}' in metrics
    assert _alerts_total(metrics) == alerts_before + 1  # the counter is process-wide: compare the increase
    assert 'jepa_monitor_open_alerts{task="Square"} 1.0' in metrics
    assert "episode" not in "".join(line for line in metrics.splitlines() if line.startswith("jepa_monitor_nmse"))


def test_alert_hysteresis_clears_and_does_not_flap(client, robot, operator, admin):
    register_task(client, "Square")
    rng = np.random.default_rng(8)
    _ingest_calibration_set(client, robot, "Square", rng, 20, 10, 0.3, 0.6)
    thr = client.post("/v1/calibrations", json={"task": "Square", "rule": "running"}, headers=admin).json()["threshold"]
    z = rng.normal(size=DIM)
    rms = np.sqrt(np.mean(z**2))

    def decide(step, nmse_target):
        # Construct z_hat so that this decision's NMSE is exactly nmse_target.
        direction = rng.normal(size=DIM)
        direction /= np.linalg.norm(direction)
        z_hat = z + direction * rms * np.sqrt(nmse_target * DIM)
        return [{"kind": "decision", "task": "Square", "episode": "hyst", "step": step, "horizon": 1,
                 "z_hat": z_hat.tolist(), "held_out": False},
                {"kind": "target", "episode": "hyst", "step": step + 1, "z": z.tolist()}]

    # Scores well above, then wobbling just below the threshold (inside the band), then clearly low.
    pattern = [2.0] * 6 + [0.95, 1.05, 0.95, 0.9, 1.1, 0.95] * 2 + [0.3] * 8
    for step, m in enumerate(pattern):
        post_batch(client, robot, decide(step, m * thr))
    alerts = client.get("/v1/alerts?task=Square", headers=operator).json()
    hyst = [a for a in alerts if a["episode_id"] == "hyst"]
    assert len(hyst) == 1 and hyst[0]["state"] == "cleared", hyst
    assert client.get("/v1/episodes/hyst", headers=operator).json()["open_alert_id"] is None
    # a cleared alert needs nobody: acknowledging it is refused and names why
    r = client.post(f"/v1/alerts/{hyst[0]['id']}/ack", headers=operator)
    assert r.status_code == 409 and "cleared" in r.json()["detail"] and "nothing to acknowledge" in r.json()["detail"]


def test_too_few_successes_for_alpha_says_how_many(client, robot, operator, admin):
    register_task(client, "Square")
    rng = np.random.default_rng(9)
    _ingest_calibration_set(client, robot, "Square", rng, 5, 5, 0.3, 0.6)
    for rule, need in (("running", 9), ("band", 17)):
        r = client.post("/v1/calibrations", json={"task": "Square", "alpha": 0.1, "rule": rule}, headers=admin)
        assert r.status_code == 409 and f"needs at least {need} successful held-out episodes" in r.json()["detail"]
        assert f"got 5; record {need - 5} more" in r.json()["detail"]
    assert client.get("/v1/calibrations", headers=operator).json() == []
    recs, _ = episode_records("after", "Square", rng, 2.0, n_steps=8, held_out=False)
    post_batch(client, robot, recs)
    ep = client.get("/v1/episodes/after", headers=operator).json()
    assert ep["open_alert_id"] is None and "no active calibration" in ep["alert_note"]


def test_calibration_refusals(client, robot, admin):
    register_task(client, "Square")
    r = client.post("/v1/calibrations", json={"task": "Square"}, headers=admin)
    assert r.status_code == 409 and "no held-out episode" in r.json()["detail"]
    assert client.post("/v1/calibrations", json={"task": "Nope"}, headers=admin).status_code == 404
    rng = np.random.default_rng(10)
    _ingest_calibration_set(client, robot, "Square", rng, 4, 0, 0.3, 0.6)
    r = client.post("/v1/calibrations", json={"task": "Square"}, headers=admin)
    assert r.status_code == 409 and "both successes and failures" in r.json()["detail"]


def test_per_checkpoint_calibration_takes_precedence(client, robot, operator, admin):
    register_task(client, "Square")
    rng = np.random.default_rng(11)
    for i in range(27):   # 18 successes: the band rule needs 17 at alpha 0.1
        fail = i % 3 == 0
        recs, _ = episode_records(f"ck-{i}", "Square", rng, 0.6 if fail else 0.3, n_steps=6, success=not fail)
        recs[0]["checkpoint"] = "ckpt-A"
        post_batch(client, robot, recs)
    _ingest_calibration_set(client, robot, "Square", rng, 20, 10, 0.3, 0.6)
    task_cal = client.post("/v1/calibrations", json={"task": "Square"}, headers=admin).json()
    ck_cal = client.post("/v1/calibrations", json={"task": "Square", "checkpoint": "ckpt-A"}, headers=admin).json()
    assert ck_cal["result"]["n_success"] + ck_cal["result"]["n_failure"] == 27
    assert task_cal["result"]["n_success"] + task_cal["result"]["n_failure"] == 57
    recs, _ = episode_records("ck-live", "Square", rng, 0.3, n_steps=6, held_out=False)
    recs[0]["checkpoint"] = "ckpt-A"
    post_batch(client, robot, recs)
    note = client.get("/v1/episodes/ck-live", headers=operator).json()["alert_note"]
    assert f"calibration #{ck_cal['id']}" in note
    listed = client.get("/v1/calibrations?task=Square&active=true", headers=operator).json()
    assert {c["id"] for c in listed} == {task_cal["id"], ck_cal["id"]}


def test_simpson_two_tasks_through_the_service(client, robot, operator, admin):
    """Per-task calibration ranks failures well while pooled raw scores are at chance; the report says so."""
    rng = np.random.default_rng(12)
    for task in ("Low", "High"):
        register_task(client, task)
    # "Low": small errors, mostly failures; "High": large errors, mostly successes (NMSE ~ noise^2).
    _ingest_calibration_set(client, robot, "Low", rng, 12, 36, 0.40, 0.60)
    _ingest_calibration_set(client, robot, "High", rng, 36, 12, 0.75, 1.10)
    per_task = {t: client.post("/v1/calibrations", json={"task": t, "rule": "running", "alpha": 0.2},
                               headers=admin).json()["auroc"]
                for t in ("Low", "High")}
    assert min(per_task.values()) > 0.85, per_task
    rep = client.get("/v1/report", headers=operator).json()
    assert rep["pooled"]["n_episodes"] == 96
    assert abs(rep["pooled"]["auroc"] - 0.5) < 0.12, rep["pooled"]
    assert "Simpson" in rep["pooled"]["warning"]


def test_sse_stream_delivers_new_alerts(tmp_path):
    settings = make_settings(tmp_path, sse_poll_s=0.05)
    with TestClient(create_app(settings)) as c:
        from monitor_service.db import Alert

        register_task(c, "Square")
        robot = new_key(c, "r", "robot", "arm1")
        op = new_key(c, "op", "operator")
        post_batch(c, robot, episode_records("e", "Square", np.random.default_rng(0), 0.3, n_steps=1)[0])
        with c.app.state.sessionmaker() as s:
            s.add(Alert(episode_id="e", task="Square", robot="arm1", step=0, score=2.0, threshold=1.0,
                        calibration_id=1, note=""))
            s.commit()
        with c.stream("GET", "/v1/alerts/stream", headers={**op, "Last-Event-ID": "0"}) as r:
            assert r.headers["content-type"].startswith("text/event-stream")
            lines = []
            for line in r.iter_lines():
                lines.append(line)
                if line.startswith("data:"):
                    break
        c.app.state.stop.set()
        assert "event: alert" in lines and "id: 1" in lines
        assert json.loads(lines[-1][5:])["episode_id"] == "e"
