"""The dashboard in headless Debian Chromium against a real uvicorn server: data and risk trajectories shown,
charts labelled, the alert life cycle (acknowledge only on open alerts), gaps shown, the key kept in
sessionStorage and taken from the URL fragment in one step."""
import json
import os

import httpx
import numpy as np
import pytest
from monitor_testkit import ADMIN, DIM, episode_records, latent_records, write_records
from script_loader import load_script

from monitor_service.cli import main
from monitor_service.db import Alert, ApiKey, make_engine, make_sessionmaker
from monitor_service.server import start_server

shot = load_script("dashboard_screenshot")
CHROMIUM, ARGS = shot.CHROMIUM, shot.ARGS   # the browser and flags the screenshot script uses

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not os.path.exists(CHROMIUM), reason="Debian chromium is not installed at /usr/bin/chromium"),
]


def test_dashboard_shows_risk_roc_and_acknowledges(tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    db_url = f"sqlite:///{tmp_path / 'monitor.db'}"
    with start_server(db_url, admin_key=ADMIN, log_path=tmp_path / "s.log") as server:
        A = {"X-API-Key": ADMIN}
        http = httpx.Client(base_url=server.url, timeout=60)
        http.put("/v1/tasks/Square", json={"latent_dim": DIM}, headers=A).raise_for_status()
        robot = {"X-API-Key": http.post("/v1/keys", json={"name": "r", "role": "robot", "robot": "arm1"},
                                        headers=A).json()["key"]}
        op_key = http.post("/v1/keys", json={"name": "alice", "role": "operator"}, headers=A).json()["key"]
        rng = np.random.default_rng(0)
        for i in range(66):   # 44 successes: the band rule ranks 22, enough for a promise at 1-20 decisions
            fail = i % 3 == 0
            recs, _ = episode_records(f"cal{i}", "Square", rng, 0.6 if fail else 0.3, n_steps=5, success=not fail)
            http.post("/v1/batch", json={"records": recs}, headers=robot).raise_for_status()
        http.post("/v1/calibrations", json={"task": "Square", "n_bootstrap": 200, "n_permutation": 200},
                  headers=A).raise_for_status()
        # Can: its successes mostly 5 decisions long, 3 of 30: too few that long for a promise at alpha 0.1
        http.put("/v1/tasks/Can", json={"latent_dim": DIM}, headers=A).raise_for_status()
        for i in range(36):
            fail = i % 4 == 0
            recs, _ = episode_records(f"can{i}", "Can", rng, 0.6 if fail else 0.3, n_steps=30 if i >= 33 else 5,
                                      success=not fail)
            http.post("/v1/batch", json={"records": recs}, headers=robot).raise_for_status()
        http.post("/v1/calibrations", json={"task": "Can", "rule": "running", "n_bootstrap": 200,
                                            "n_permutation": 200}, headers=A).raise_for_status()
        # a failure that ran to 25 decisions, a length the calibration holds 3 successes of: no promise covers it
        recs, _ = episode_records("can-bad", "Can", rng, 2.0, n_steps=25, held_out=False, success=False)
        can_alert = http.post("/v1/batch", json={"records": recs}, headers=robot).json()["alerts_raised"][0]
        recs, _ = episode_records("live-bad", "Square", rng, 2.0, n_steps=8, held_out=False)
        alert_id = http.post("/v1/batch", json={"records": recs}, headers=robot).json()["alerts_raised"][0]
        # an episode that alerted and then failed: its alert is resolved by the outcome, nothing to acknowledge
        recs, _ = episode_records("done-bad", "Square", rng, 2.0, n_steps=8, held_out=False, success=False)
        done_id = http.post("/v1/batch", json={"records": recs}, headers=robot).json()["alerts_raised"][0]
        # a live episode whose decision at step 3 never came: a gap
        recs, _ = episode_records("gappy", "Square", rng, 0.3, n_steps=6, held_out=False)
        http.post("/v1/batch", json={"records": recs[:6] + recs[8:]}, headers=robot).raise_for_status()

        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            try:
                page = browser.new_page()
                requests = []
                page.on("request", lambda req: requests.append(req.url))
                page.goto(server.url + "/dashboard")
                page.fill("#api-key", op_key)
                page.click("#connect")
                page.wait_for_selector("#tasks tr[data-task='Square']")
                page.wait_for_selector("svg.roc[data-task='Square'] polyline")
                assert page.locator("svg.histogram[data-task='Square'] rect").count() > 0
                assert "live-bad" in page.inner_text("#episodes")
                # the live episode's risk trajectory against the band threshold, points above it in red
                traj = page.locator("svg.trajectory[data-episode='live-bad'][data-signal='nmse']")
                assert page.locator("#tasks tr[data-task='Square'] td.detector").inner_text().startswith("nmse, band")
                traj.locator("polyline.risk").wait_for()
                assert traj.locator("polyline.threshold").count() == 1
                assert traj.locator("circle[fill='#b00020']").count() >= 2
                assert "band" in traj.locator("text.title").text_content()
                # every chart has its axis labels, and its title fits inside it
                for chart in ("svg.histogram[data-task='Square']", "svg.roc[data-task='Square']",
                              "svg.trajectory[data-episode='live-bad']"):
                    loc = page.locator(chart)
                    assert loc.locator("text.xlabel").text_content() and loc.locator("text.ylabel").text_content()
                    title, outer = loc.locator("text.title").bounding_box(), loc.bounding_box()
                    assert title["x"] >= outer["x"] and title["x"] + title["width"] <= outer["x"] + outer["width"]
                assert "median NMSE" in page.locator("svg.histogram[data-task='Square'] text.xlabel").text_content()
                # the key lives in this tab's sessionStorage only
                assert page.evaluate("sessionStorage.getItem('jepaMonitorKey')") == op_key
                assert page.evaluate("localStorage.getItem('jepaMonitorKey')") is None
                assert "WARNING" in page.inner_text("#pooled")
                row = page.locator(f"#alerts tr[data-alert='{alert_id}']")
                assert row.count() == 1 and row.locator("td.state").inner_text() == "open"
                done = page.locator(f"#alerts tr[data-alert='{done_id}']")
                assert done.locator("td.state").inner_text() == "resolved: failure"
                assert done.locator("button.ack").count() == 0, "a resolved alert offers no Acknowledge"
                assert "1 missing at 3" in page.locator("#episodes tr[data-episode='gappy'] td.gaps").inner_text()
                # which lengths carry the false-alert promise, per task, and the alert that no promise covers
                square = page.locator("#tasks tr[data-task='Square'] td.regimes")
                assert square.inner_text().startswith("0.1 in each of 1-") and "no promise" not in square.inner_text()
                can = page.locator("#tasks tr[data-task='Can'] td.regimes.no-promise")
                assert "no promise at 21-" in can.inner_text() and "(3 successes)" in can.inner_text()
                can_row = page.locator(f"#alerts tr[data-alert='{can_alert}'] td.state")
                assert "no false-alert promise" in can_row.inner_text()
                assert "3 calibration successes" in can_row.get_attribute("title")   # the note says why
                row.locator("button.ack").click()
                page.wait_for_selector(f"#alerts tr[data-alert='{alert_id}'] >> text=alice")
                assert row.locator("td.state").inner_text() == "acknowledged" and row.locator("button.ack").count() == 0
                assert all(u.startswith(server.url) for u in requests), "the page must not fetch anything external"

                # one step: a fresh tab opened with the key in the URL fragment shows the data at once, and the
                # key leaves the address bar (and never reaches the server: fragments are not sent)
                fresh = browser.new_context().new_page()
                fresh.goto(f"{server.url}/dashboard#key={op_key}")
                fresh.wait_for_selector("#tasks tr[data-task='Square']")
                fresh.wait_for_function("document.getElementById('status').textContent === 'connected'")
                assert op_key not in fresh.url
                assert fresh.evaluate("sessionStorage.getItem('jepaMonitorKey')") == op_key
            finally:
                browser.close()
        assert op_key not in (tmp_path / "s.log").read_text()
        engine = make_engine(db_url)
        with make_sessionmaker(engine)() as s:
            alert = s.get(Alert, alert_id)
            assert alert.acknowledged_by == "alice" and alert.acknowledged_at is not None
            assert alert.note == "acknowledged from dashboard"
        engine.dispose()
        http.close()


def test_dashboard_shows_three_tasks_each_with_its_own_threshold_alerts_and_trajectories(tmp_path):
    """`jepa-monitor tasks-study --keep DIR --in-flight 3` on three tasks whose successes predict their future with
    different errors, then scripts/dashboard_screenshot.py on the kept database: each task's row shows its own
    threshold (as the API has it), its three running episodes each get a risk trajectory against that threshold,
    and a busy task hides no other's. The study's own keys are revoked in the kept database."""
    pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    files = {task: write_records(tmp_path / f"{task}.jsonl.gz", latent_records(40, 14, seed=seed, noise=noise))
             for task, seed, noise in (("PushT", 11, (0.5, 1.0)), ("Lift", 12, (0.2, 0.6)), ("Can", 13, (0.3, 0.8)))}
    keep = tmp_path / "kept"
    argv = ["tasks-study", *[a for t, f in files.items() for a in ("--task", f"{t}={f}")], "--keep", str(keep),
            "--in-flight", "3", "--no-progress", "--out", str(tmp_path / "study.json")]
    assert main(argv) == 0
    assert main(argv) == 2, "a second study into the same kept database is refused"
    study = json.loads((tmp_path / "study.json").read_text())

    png = tmp_path / "dashboard.png"
    checked = shot.screenshot(f"sqlite:///{keep / 'tasks_study.db'}", png)
    assert set(checked) == {"PushT", "Lift", "Can"}
    thresholds = {t: c["threshold"] for t, c in checked.items()}
    assert thresholds["Lift"] < thresholds["Can"] < thresholds["PushT"]   # each its own, from its own noise
    for task, c in checked.items():
        assert c["threshold"] == pytest.approx(study["tasks"][task]["calibration"]["threshold"])
        assert c["live"] == 3 and len(c["trajectories"]) == 3
        assert all(e.startswith(f"{task}-live-") for e in c["trajectories"])
        assert c["alerted_episodes"] == study["tasks"][task]["service"]["alerted_episodes"]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    engine = make_engine(f"sqlite:///{keep / 'tasks_study.db'}")
    with make_sessionmaker(engine)() as s:
        assert all(k.revoked_at is not None for k in s.query(ApiKey)), "no key of the study or the script lives on"
    engine.dispose()
