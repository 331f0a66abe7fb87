"""openpi part of `make interop`: PushT episodes driven through `jepa-policy serve` by docs/serving.md's robot loop,
run as written with the published openpi-client (its WebsocketClientPolicy and ActionChunkBroker, in their own
venv), compared action by action with the same checkpoint's in-process ``Policy.act`` on the same observations.
``drive_documented_loop`` is also what tests/jepa_policy/test_serve_openpi.py runs."""
from __future__ import annotations

import io
import json
import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PEER = ROOT / "scripts" / "interop_openpi_peer.py"
DOC = ROOT / "docs" / "serving.md"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _send(proc, **arrays) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    proc.stdin.write(struct.pack("<I", len(buf.getvalue())) + buf.getvalue())
    proc.stdin.flush()


def _recv(proc) -> dict:
    head = proc.stdout.read(4)
    if len(head) < 4:
        raise RuntimeError(f"the openpi peer ended: {proc.stderr.read().decode()[-2000:]}")
    (n,) = struct.unpack("<I", head)
    data = np.load(io.BytesIO(proc.stdout.read(n)), allow_pickle=False)
    return {k: data[k] for k in data.files}


def _checkpoint(work: Path) -> Path:
    from jepa_envs.datasets.hdf5 import write_dataset
    from jepa_envs.tasks.pusht_expert import generate_demos

    demos = work / "pusht-openpi.hdf5"
    episodes, env_args = generate_demos(4, seed=7)
    write_dataset(demos, episodes, env_args)
    out = work / "openpi-run"
    subprocess.run([sys.executable, "-m", "jepa_policy.cli", "train", "--task", "PushT", "--preset", "quick",
                    "--dataset", str(demos), "--steps", "20", "--warmup-steps", "5", "--eval-every", "0",
                    "--out", str(out), "--no-progress"], check=True, capture_output=True)
    return out / "checkpoints" / "latest.pt"


def drive_documented_loop(py: str, port: int, api_key: str, policy, episodes: int = 1, max_steps: int | None = None,
                          seed: int = 11) -> dict:
    """docs/serving.md's loop in the openpi-client venv ``py`` drives PushT episodes against the server on ``port``
    while this process steps the environment and asks ``policy`` (the same checkpoint, in-process) for its action
    on every observation: the largest |served - in-process| difference, steps, successes, the metadata read."""
    import gymnasium as gym

    import jepa_envs  # noqa: F401

    peer = subprocess.Popen([py, str(PEER), str(DOC), "127.0.0.1", str(port), api_key, str(episodes)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    env = gym.make("JEPA/PushT-v0", image_size=policy.spec.image_size)   # the metadata's observation size
    diffs, steps, successes = [], 0, 0
    try:
        for episode in range(episodes):
            policy.reset()
            obs, _ = env.reset(seed=seed + episode)
            _send(peer, done=np.int64(0), success=np.int64(0), **obs)
            success = False
            for t in range(max_steps or env.spec.max_episode_steps):
                served = _recv(peer)["action"]
                diffs.append(float(np.abs(served - policy.act(obs)).max()))
                obs, _, terminated, truncated, info = env.step(served)
                steps += 1
                success = success or bool(info["is_success"])
                done = terminated or truncated or t + 1 == (max_steps or env.spec.max_episode_steps)
                _send(peer, done=np.int64(done), success=np.int64(success), **obs)
                if done:
                    break
            successes += success
        metadata = json.loads(str(_recv(peer)["metadata"]))
        peer.wait(timeout=30)
    finally:
        if peer.poll() is None:
            peer.kill()
        env.close()
    return {"steps": steps, "episodes": episodes, "successes": successes, "max_abs_action_diff": max(diffs),
            "bit_equal": max(diffs) == 0.0, "metadata": metadata}


def check_openpi(py: str, work: Path) -> dict:
    import torch

    from jepa_policy.policy import Policy

    checkpoint = _checkpoint(work)
    port, key = _free_port(), "interop-key"
    server = subprocess.Popen([sys.executable, "-m", "jepa_policy.cli", "serve", "--checkpoint", str(checkpoint),
                               "--port", str(port), "--threads", "1"], env={**os.environ, "JEPA_POLICY_API_KEY": key},
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    result: dict = {}
    try:
        deadline = time.monotonic() + 60
        while True:   # the server is up when /healthz answers
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=1) as s:
                    s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
                    if b"OK" in s.recv(200):
                        break
            except OSError:
                pass
            if time.monotonic() > deadline or server.poll() is not None:
                raise RuntimeError(f"jepa-policy serve did not start: {server.stderr.read().decode()[-2000:]}")
            time.sleep(0.2)
        # without the key, openpi-client is turned away at the handshake
        refused = subprocess.run([py, "-c", "from openpi_client.websocket_client_policy import WebsocketClientPolicy;"
                                  f"WebsocketClientPolicy('127.0.0.1', {port})"], capture_output=True, text=True,
                                 timeout=60)
        result["refused_without_key"] = refused.returncode != 0 and "401" in refused.stderr
        torch.set_num_threads(1)   # as the server (--threads 1): the same arithmetic order, so equal floats
        policy = Policy.from_checkpoint(checkpoint)
        result.update(drive_documented_loop(py, port, key, policy, episodes=2))
        meta = result.pop("metadata")
        result["metadata"] = {k: meta[k] for k in ("task", "observation", "obs_steps", "action", "control_hz")}
        result["inferences_per_episode"] = int(np.ceil(result["steps"] / result["episodes"] / policy.n_action_steps))
        result["ok"] = result["refused_without_key"] and result["bit_equal"] and result["steps"] > 0
    finally:
        server.terminate()
        server.wait(timeout=30)
    return result


def print_openpi(result: dict) -> None:
    meta = result["metadata"]
    print("openpi-client 0.1.2 running docs/serving.md's loop (WebsocketClientPolicy + ActionChunkBroker) against "
          "jepa-policy serve")
    print(f"  metadata: task {meta['task']}, observation {meta['observation']}, chunk {meta['action']['chunk']}")
    print(f"  {result['episodes']} episodes, {result['steps']} steps, {result['successes']} successes; actions vs "
          f"in-process Policy.act: max |diff| {result['max_abs_action_diff']:.3g} "
          f"({'bit-equal' if result['bit_equal'] else 'DIFFER'}); refused without the API key: "
          f"{result['refused_without_key']}")
