"""Alert state machine and webhook delivery with retries to a real HTTP receiver on 127.0.0.1."""
import http.server
import json
import re
import threading
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient
from monitor_testkit import ADMIN, episode_records, make_settings, new_key, post_batch, register_task
from sqlalchemy import select

from monitor_service.alerts import AlertState, step_alert
from monitor_service.app import create_app
from monitor_service.db import WebhookDelivery


def run(scores, threshold=1.0, debounce=2, clear_ratio=0.8):
    state, events = AlertState(), []
    for s in scores:
        state, event = step_alert(state, s, threshold, debounce, clear_ratio * threshold)
        events.append(event)
    return state, events


def test_debounce_needs_consecutive_crossings():
    _, events = run([1.5, 0.9, 1.5, 0.9, 1.5])
    assert events == [None] * 5
    state, events = run([1.5, 1.5])
    assert events == [None, "raise"] and state.raised


def test_hysteresis_band_prevents_flapping_and_clears_below_band():
    _, events = run([2, 2, 0.9, 1.1, 0.85, 0.95, 0.9, 1.2])
    assert events.count("raise") == 1 and "clear" not in events
    _, events = run([2, 2, 0.7, 0.9, 0.7, 0.7, 2, 2])
    assert events == [None, "raise", None, None, None, "clear", None, "raise"]


class Receiver:
    """A real HTTP server that fails the first ``fail_first`` posts with 500, then records the bodies."""

    def __init__(self, fail_first=0):
        self.bodies, self.attempts, self.fail_first = [], 0, fail_first
        outer = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                outer.attempts += 1
                if outer.attempts <= outer.fail_first:
                    self.send_response(500)
                else:
                    outer.bodies.append(json.loads(body))
                    self.send_response(204)
                self.end_headers()

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hook"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()
        self.thread.join()


@pytest.fixture
def receiver():
    r = Receiver(fail_first=2)
    yield r
    r.close()


def _raise_one_alert(c):
    register_task(c, "Square")
    robot = new_key(c, "r", "robot", "arm1")
    rng = np.random.default_rng(0)
    for i in range(30):
        fail = i % 3 == 0
        records, _ = episode_records(f"cal{i}", "Square", rng, 0.6 if fail else 0.3, n_steps=5, success=not fail)
        post_batch(c, robot, records)
    assert c.post("/v1/calibrations", json={"task": "Square"}, headers={"X-API-Key": ADMIN}).status_code == 201
    r = post_batch(c, robot, episode_records("bad", "Square", rng, 2.0, n_steps=8, held_out=False)[0])
    assert len(r.json()["alerts_raised"]) == 1
    return r.json()["alerts_raised"][0]


def test_webhook_retries_until_delivered(tmp_path, receiver):
    settings = make_settings(tmp_path, webhook_urls=[receiver.url], webhook_backoff_s=0.05)
    with TestClient(create_app(settings)) as c:
        alert_id = _raise_one_alert(c)
        # the receiver holds the body before the server has written the outcome of that attempt: wait for both
        deadline, row = time.time() + 20, None
        while time.time() < deadline:
            with c.app.state.sessionmaker() as s:
                d = s.scalar(select(WebhookDelivery))
                row = None if d is None else (d.status, d.attempts, d.last_error)
            if receiver.bodies and row is not None and row[0] != "pending":
                break
            time.sleep(0.05)
        assert receiver.attempts == 3 and len(receiver.bodies) == 1
        assert receiver.bodies[0]["id"] == alert_id and receiver.bodies[0]["episode_id"] == "bad"
        assert row == ("delivered", 3, "")
        metrics = c.get("/metrics", headers={"X-API-Key": ADMIN}).text
        failures = float(re.search(r"^jepa_monitor_webhook_failures_total ([0-9.]+)$", metrics, re.M).group(1))
        assert failures >= 2  # process-wide counter: other tests in this process may add to it


def test_webhook_gives_up_after_max_attempts(tmp_path):
    receiver = Receiver(fail_first=100)
    try:
        settings = make_settings(tmp_path, webhook_urls=[receiver.url], webhook_backoff_s=0.01, webhook_max_attempts=3)
        with TestClient(create_app(settings)) as c:
            _raise_one_alert(c)
            deadline = time.time() + 20
            status = None
            while time.time() < deadline:
                with c.app.state.sessionmaker() as s:
                    status = s.scalar(select(WebhookDelivery.status))
                if status == "failed":
                    break
                time.sleep(0.05)
            assert status == "failed" and receiver.attempts == 3
    finally:
        receiver.close()
