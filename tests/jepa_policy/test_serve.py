"""jepa-policy serve over openpi's websocket protocol: what openpi-client sees (metadata, packing, replies, errors as
text frames), the same actions as in-process act, several robots at once without cross-talk and batched, every bad
request answered with the connection kept, auth, and the monitor inside (real service, and one that is down).
The published openpi-client itself drives a whole episode in `make interop` (its numpy < 2 needs its own venv)."""
from __future__ import annotations

import threading
import time
from collections import deque

import gymnasium as gym
import httpx
import msgpack
import numpy as np
import pytest
import websockets
from _serve_helpers import GOOD, checkpoint, client, events, serve, unpaced  # noqa: F401 (fixtures)

import jepa_envs  # noqa: F401
from jepa_policy.policy import Policy
from jepa_policy.serve import PolicyServer, ServeConfig, pack, unpack

pytestmark = pytest.mark.timeout(300)
_client = client


def _frame(env_obs) -> dict:
    return {k: np.asarray(v) for k, v in env_obs.items()}


def test_metadata_and_a_served_episode_equal_in_process_act(serve, checkpoint):
    server = serve()
    ws, meta = _client(server)
    assert meta["task"] == "PushT" and meta["obs_steps"] == 2 and meta["action"]["chunk"] == [8, 2]
    assert meta["observation"] == {"top_image": {"shape": [32, 32, 3], "dtype": "uint8"},
                                   "agent_pos": {"shape": [2], "dtype": "float32"}}
    local = Policy.from_checkpoint(checkpoint)
    env = gym.make("JEPA/PushT-v0", image_size=32)
    obs, _ = env.reset(seed=5)
    chunk = None
    for t in range(24):
        ws.send(pack(_frame(obs)))   # a loop that calls every step: the server keeps the history
        reply = unpack(ws.recv())
        assert reply["step"] == t and reply["actions"].shape == (8, 2) and reply["actions"].dtype == np.float32
        assert reply["history_padded"] is (t == 0)   # only the first frame's history repeats it, as in-process
        assert {"infer_ms", "queue_ms", "prev_total_ms"} <= set(reply["server_timing"])
        if t % 8 == 0:
            chunk = reply["actions"]
        action = local.act(obs)
        assert np.allclose(chunk[t % 8], action, atol=1e-5), t   # the same decisions as the in-process runtime
        obs, *_ = env.step(action)
    ws.close()
    env.close()


def test_client_side_history_and_full_chunk(serve, checkpoint):
    """A loop that calls once per chunk sends its own two newest frames; the server decides from them."""
    server = serve()
    ws, _ = _client(server)
    env = gym.make("JEPA/PushT-v0", image_size=32)
    obs0, _ = env.reset(seed=2)
    obs1, *_ = env.step(obs0["agent_pos"])
    stacked = {k: np.stack([obs0[k], obs1[k]]) for k in obs0}
    ws.send(pack({**stacked, "step": 1, "full_chunk": True}))
    reply = unpack(ws.recv())
    local = Policy.from_checkpoint(checkpoint)
    chunk, _ = local.decide_from([obs0, obs1]).actions, None
    assert reply["actions"].shape == (16, 2) and np.allclose(reply["actions"], chunk, atol=1e-5)
    assert reply["history_padded"] is False   # two real frames: nothing padded
    ws.send(pack({**_frame(obs1), "step": 9}))   # a gap in the steps: the history restarts, as at an episode start
    assert unpack(ws.recv())["history_padded"] is True
    ws.send(pack({**_frame(obs0), "step": 10}))  # the next step: two real frames again
    assert unpack(ws.recv())["history_padded"] is False
    env.close()


def test_the_documented_chunk_loop_equals_in_process_act(serve, checkpoint):
    """docs/serving.md's loop (ActionChunkBroker: one request per chunk, the newest obs_steps frames stacked with
    their step) drives an episode bit-equal to in-process act, and only its first reply says history_padded (one
    frame at step 0); a loop sending the newest frame alone, without its step, would decide from frames 0 and 8."""
    server = serve()
    ws, meta = _client(server)
    local = Policy.from_checkpoint(checkpoint)
    env = gym.make("JEPA/PushT-v0", image_size=32)
    obs, _ = env.reset(seed=3)
    frames, chunk, padded = deque(maxlen=meta["obs_steps"]), None, []
    for step in range(40):
        frames.append(obs)
        if step % meta["action"]["chunk"][0] == 0:   # what the broker does: a request when its chunk runs out
            ws.send(pack({**{k: np.stack([f[k] for f in frames]) for k in obs}, "episode": "e1", "step": step}))
            reply = unpack(ws.recv())
            chunk = reply["actions"]
            padded.append(reply["history_padded"])
        action = chunk[step % 8]
        assert np.array_equal(action, local.act(obs)), step   # bit-equal: same weights, threads and batch size
        obs, *_ = env.step(action)
    assert padded == [True, False, False, False, False]
    ws.close()
    env.close()


BAD = [
    (b"\x93\xff\xfe", "is not msgpack as openpi-client packs it"),
    ("a text frame", "send binary frames packed with msgpack"),
    (pack({"agent_pos": np.zeros(2, np.float32)}), "the observation lacks ['top_image']"),
    (pack({"top_image": np.zeros((84, 84, 3), np.uint8), "agent_pos": np.zeros(2, np.float32)}),
     "top_image has shape [84, 84, 3]; send [32, 32, 3]"),
    (pack({"top_image": np.zeros((32, 32, 3), np.float32), "agent_pos": np.zeros(2, np.float32)}),
     "top_image has dtype float32; send uint8"),
    (pack({"top_image": np.zeros((32, 32, 3), np.uint8), "agent_pos": np.array([np.nan, 1], np.float32)}),
     "agent_pos has NaN or infinite values"),
    (pack({"top_image": np.zeros((3, 32, 32, 3), np.uint8), "agent_pos": np.zeros((3, 2), np.float32)}),
     "with n <= 2"),
    (pack({"top_image": np.zeros((32, 32, 3), np.uint8), "agent_pos": np.zeros(2, np.float32), "step": "x"}),
     "'step' must be int"),
    (pack([1, 2, 3]), "a request is a map of observation keys"),
    (pack({**GOOD, "agent_pos": np.array([4.6e18, 1.0], np.float32)}),   # was taken: only finiteness was checked
     "agent_pos holds 4.6e+18 at index [0], far outside the range the policy was trained on"),
    (pack({**GOOD, "agent_pos": np.array([1e300, 1.0])}), "agent_pos has NaN or infinite values (or values beyond"),
    (pack({**GOOD, "x": {b"__npgeneric__": True, b"data": 1e10, b"dtype": "<f2"}}), "does not fit dtype float16"),
    (pack({b"\xff\xfe": 1, **GOOD}), "the map key b'\\xff\\xfe' is not UTF-8 text"),
    (msgpack.packb({b"\xff": 1}, use_bin_type=False), "is not msgpack as openpi-client packs it"),   # str, not UTF-8
    (pack({**GOOD, "agent_pos": [[1.0, 2.0], [3.0]]}), "agent_pos holds a list of 1 items at depth 2"),
    (pack({**GOOD, "agent_pos": [1.0, "x"]}), "agent_pos holds a str where a number goes"),
    (pack({**GOOD, "step": {b"__npgeneric__": True, b"data": 4_000_000, b"dtype": "|V8"}}),
     "arrays of dtype '|V8' are refused"),
    (pack({**GOOD, "top_image": {b"__ndarray__": True, b"data": b"", b"dtype": "|O", b"shape": [0]}}),
     "arrays of dtype '|O' are refused"),
    (pack({**GOOD, "top_image": {b"__ndarray__": True, b"data": b"x", b"dtype": "|u1", b"shape": [10**12]}}),
     "shape must be a list of at most 8 sizes"),
    (pack({**GOOD, "top_image": {b"__ndarray__": True, b"data": b"x", b"dtype": "|u1", b"shape": [2, 3]}}),
     "an array's data has 1 bytes, its shape [2, 3] of uint8 needs 6"),
    (msgpack.packb({"x": msgpack.ExtType(5, b"1"), **{k: v.tolist() for k, v in GOOD.items()}}),
     "msgpack extension type 5 is refused"),
]


def test_every_bad_request_gets_a_message_and_the_connection_survives(unpaced, serve, events):
    """Each bad request is answered with its problem and the connection goes on serving; a connection takes up to
    7 refused requests in a row (the 8th closes it: test_serve_hostile), so each takes 4 of them here."""
    server = serve()
    connections = []
    for i, (frame, message) in enumerate(BAD):
        if i % 4 == 0:
            connections.append(_client(server)[0])
        ws = connections[-1]
        ws.send(frame)
        reply = ws.recv()
        assert isinstance(reply, str) and message in reply, (message, reply[:300])
        ws.send(pack(GOOD))   # and the same connection still serves
        assert unpack(ws.recv())["actions"].shape == (8, 2)
    for ws in connections:
        ws.close()
    rejected = [e for e in events() if e["event"] == "rejected"]
    assert len(rejected) == len(BAD) and len({e["session"] for e in rejected}) == len(connections)
    assert all(e["peer"].startswith("127.0.0.1:") and e["ts"].endswith("Z") for e in rejected)
    assert [message in e["problem"] for e, (_, message) in zip(rejected, BAD)] == [True] * len(BAD)


def test_a_client_leaving_mid_request_and_a_full_queue(serve, events):
    server = serve(max_queue=1)
    good = pack({"top_image": np.zeros((32, 32, 3), np.uint8), "agent_pos": np.zeros(2, np.float32)})
    ws, _ = _client(server)
    ws.send(good)
    ws.close()   # gone before its reply
    clients = [_client(server)[0] for _ in range(6)]
    server.batcher.executor.submit(time.sleep, 1.0)   # the model is busy: one request is taken, one waits
    for ws in clients:
        ws.send(good)
        time.sleep(0.05)
    replies = [ws.recv() for ws in clients]
    refused = [r for r in replies if isinstance(r, str)]
    assert len(refused) == 4 and all("the server is busy: 1 requests are waiting (limit 1)" in r for r in refused)
    for ws in clients:   # a refused request does not close the connection
        ws.send(good)
        reply = ws.recv()
        while isinstance(reply, str):
            time.sleep(0.05)
            ws.send(good)
            reply = ws.recv()
        assert unpack(reply)["actions"].shape == (8, 2)
        ws.close()
    busy = [e for e in events() if e["event"] == "busy"]
    assert len(busy) >= 4 and all({"ts", "peer", "session", "queue"} <= set(e) for e in busy)


def test_robots_at_once_keep_their_own_episodes_and_share_batches(serve, checkpoint):
    """Eight robots, each with its own episode: every reply equals that robot's own in-process decision, and
    requests that arrive together run in one forward pass."""
    server = serve(max_batch=8)
    local = Policy.from_checkpoint(checkpoint)
    rng = np.random.default_rng(0)
    frames = [{"top_image": rng.integers(0, 255, (32, 32, 3), dtype=np.uint8),
               "agent_pos": rng.uniform(0, 512, 2).astype(np.float32)} for _ in range(8)]
    expected = [local.decide_from([f]).actions[:8] for f in frames]
    results = [None] * 8
    barrier = threading.Barrier(8)

    def robot(i):
        ws, _ = _client(server)
        barrier.wait()
        ws.send(pack({**frames[i], "episode": f"robot-{i}"}))
        results[i] = unpack(ws.recv())
        ws.close()
    threads = [threading.Thread(target=robot, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i, reply in enumerate(results):
        assert reply["episode"] == f"robot-{i}"
        assert np.allclose(reply["actions"], expected[i], atol=1e-4), i
    assert max(r["server_timing"]["batch"] for r in results) > 1
    assert server.batcher.items == 8 and server.batcher.batches < 8


def test_auth_and_a_network_bind(serve, checkpoint, events, caplog):
    server = serve(api_key="s3cret")
    with pytest.raises(websockets.InvalidStatus, match="401"):
        _client(server)
    with pytest.raises(websockets.InvalidStatus, match="401"):
        _client(server, headers={"Authorization": "Api-Key wrong"})
    # two headers, even both right, were an HTTP 500 with a traceback in the log (Headers.get raised)
    for pair in (["Api-Key s3cret", "Api-Key s3cret"], ["Api-Key wrong", "Api-Key s3cret"]):
        with pytest.raises(websockets.InvalidStatus, match="401"):
            _client(server, headers=[("Authorization", value) for value in pair])
    assert [e.get("problem") for e in events() if e["event"] == "unauthorized"] == [
        "no Authorization header", "a wrong key", "2 Authorization headers", "2 Authorization headers"]
    assert not [r for r in caplog.records if r.levelname == "ERROR"], "a rejected handshake logged an error"
    ws, meta = _client(server, headers={"Authorization": "Api-Key s3cret"})
    assert meta["task"] == "PushT"
    ws.close()
    assert httpx.get(f"http://127.0.0.1:{server.port}/healthz").text == "OK\n"
    with pytest.raises(ValueError, match="reachable from the network: pass --api-key"):
        PolicyServer(Policy.from_checkpoint(checkpoint), ServeConfig(host="0.0.0.0", port=0))


def _episode(ws, env, steps, episode, outcome=None):
    obs, _ = env.reset(seed=1)
    replies = []
    for t in range(steps):
        ws.send(pack({**_frame(obs), "episode": episode}))
        replies.append(unpack(ws.recv()))
        obs, *_ = env.step(replies[-1]["actions"][0])
    if outcome is not None:
        ws.send(pack({"episode": episode, "outcome": outcome}))
        replies.append(unpack(ws.recv()))
    return replies


def test_the_monitor_inside_scores_decisions_and_never_blocks(serve, tmp_path):
    from monitor_service.server import start_server

    admin = "serve-test-admin"
    with start_server(f"sqlite:///{tmp_path / 'monitor.db'}", admin_key=admin) as monitor:
        with httpx.Client(base_url=monitor.url, headers={"X-API-Key": admin}) as http:
            assert http.put("/v1/tasks/PushT", json={}).status_code == 200
            key = http.post("/v1/keys", json={"name": "arm", "role": "robot", "robot": "arm"}).json()["key"]
            server = serve(monitor_url=monitor.url, monitor_key=key, robot="arm")
            ws, meta = _client(server)
            assert meta["monitor"] == {"task_id": "PushT"}
            env = gym.make("JEPA/PushT-v0", image_size=32)
            replies = _episode(ws, env, 12, "ep-a", outcome=True)
            scored = [s for r in replies for s in r.get("monitor", {}).get("scored", [])]
            # every step is a decision here (the loop calls every step); decision t is scored by frame t + 4
            assert [s["target_step"] - s["decision_step"] for s in scored] == [4] * 8
            assert all(s["nmse"] >= 0 for s in scored) and replies[-1]["ended"] == {"episode": "ep-a", "success": True}
            assert server.monitor.flush(30)
            ep = http.get("/v1/episodes/ep-a").json()
            assert ep["n_decisions"] == 12 and ep["n_scored"] == 8 and ep["success"] is True
            monitored = {d["step"]: d["nmse"] for d in ep["decisions"] if d["nmse"] is not None}
            assert all(monitored[s["decision_step"]] == pytest.approx(s["nmse"], rel=1e-5) for s in scored)
            # z_now went with every decision (the current frame, encoded in the same pass): the service scored
            # the persistence control and nmse_ratio of every scored decision, as it does for jepa-policy robot
            rows = {d["step"]: d for d in ep["decisions"] if d["nmse"] is not None}
            assert len(rows) == 8 and all(d["nmse_persistence"] is not None and d["nmse_persistence"] > 0 and
                                          d["nmse_ratio"] == pytest.approx(d["nmse"] / d["nmse_persistence"], rel=1e-6)
                                          for d in rows.values())
            ws.close()
            env.close()


def test_a_down_monitor_costs_the_replies_nothing(serve, events):
    """The monitor is unreachable: replies come at the same pace and the records wait in the bounded buffer (the
    records still undelivered at stop are counted in the event log). The reply to an outcome names the episode it
    ended everywhere (its monitor state named the next one)."""
    server = serve(monitor_url="http://127.0.0.1:9", monitor_key="k", monitor_flush_s=0.2)
    ws, _ = _client(server)
    env = gym.make("JEPA/PushT-v0", image_size=32)
    start = time.perf_counter()
    replies = _episode(ws, env, 16, "ep-down", outcome=False)
    per_request = (time.perf_counter() - start) / 17
    assert per_request < 0.5, f"{per_request * 1e3:.0f} ms per request with the monitor down"
    assert replies[-2]["monitor"]["pending_records"] > 0 and replies[-2]["monitor"]["dropped_records"] == 0
    ended = replies[-1]
    assert ended["episode"] == ended["ended"]["episode"] == ended["monitor"]["episode"] == "ep-down"
    ws.send(pack(GOOD))   # no id: the next episode gets a new one
    assert unpack(ws.recv())["episode"] not in ("ep-down", "")
    ws.close()
    server.stop()
    lost = [e for e in events() if e["event"] == "stop"]
    assert lost and lost[0]["monitor_records_lost"] > 0
    env.close()


def test_named_scores_go_to_the_monitor_equal_to_in_process_acting(checkpoint, pusht_demo_file, tmp_path):
    """``monitor_scores`` all: each served decision sends STAC (against the session's previous chunk) and the
    embedding scores of fitted detectors, equal to what ``Policy`` computes in-process for the same frames; the
    default sends none (a task that registered no signals keeps working)."""
    import shutil

    from jepa_policy.cli import main as policy_main
    from jepa_policy.serve import PolicyServer, ServeConfig
    from monitor_service.server import start_server

    ck = tmp_path / "ck.pt"
    shutil.copy(checkpoint, ck)
    assert policy_main(["fit-detectors", "--checkpoint", str(ck), "--dataset", str(pusht_demo_file),
                        "--samples", "256", "--device", "cpu"]) == 0
    names = ["stac", "rnd", "pca_kmeans", "mahalanobis"]
    admin = "serve-test-admin"
    with start_server(f"sqlite:///{tmp_path / 'monitor.db'}", admin_key=admin) as monitor:
        with httpx.Client(base_url=monitor.url, headers={"X-API-Key": admin}) as http:
            assert http.put("/v1/tasks/PushT", json={"signals": names}).status_code == 200
            key = http.post("/v1/keys", json={"name": "arm", "role": "robot", "robot": "arm"}).json()["key"]
            servers = [PolicyServer(Policy.from_checkpoint(ck), ServeConfig(
                port=0, monitor_url=monitor.url, monitor_key=key, robot="arm", monitor_scores=scores), str(ck))
                .start_in_thread() for scores in (None, ())]
            try:
                env = gym.make("JEPA/PushT-v0", image_size=32)
                for server, episode in zip(servers, ("ep-all", "ep-none")):
                    ws, _ = _client(server)
                    _episode(ws, env, 6, episode, outcome=False)
                    ws.close()
                    assert server.monitor.flush(30)
                sent = {d["step"]: d["scores"] for d in http.get("/v1/episodes/ep-all").json()["decisions"]}
                assert all(d["scores"] is None for d in http.get("/v1/episodes/ep-none").json()["decisions"])
                local = Policy.from_checkpoint(ck)            # the same frames, acting in-process, every step
                obs, _ = env.reset(seed=1)
                for t in range(6):
                    local.predict({k: obs[k] for k in GOOD})
                    want = {k: float(v) for k, v in local.last_decision.scores.items() if np.isfinite(v)}
                    assert set(sent[t]) == set(want) == (set(names) if t else set(names) - {"stac"})
                    assert all(sent[t][k] == pytest.approx(want[k], rel=1e-5, abs=1e-9) for k in want)
                    obs, *_ = env.step(local.last_decision.actions[0])
                env.close()
            finally:
                for server in servers:
                    server.stop()
