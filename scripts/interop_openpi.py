"""openpi part of `make interop`: a PushT episode driven through `jepa-policy serve` by the published
openpi-client (its WebsocketClientPolicy and ActionChunkBroker, in their own venv), compared action by action
with the same checkpoint's in-process ``Policy.act`` on the same observations."""
from __future__ import annotations

import io
import json
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PEER = ROOT / "scripts" / "interop_openpi_peer.py"


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
                    "--out-dir", str(out), "--no-progress"], check=True, capture_output=True)
    return out / "checkpoints" / "latest.pt"


def check_openpi(py: str, work: Path) -> dict:
    import gymnasium as gym
    import torch

    import jepa_envs  # noqa: F401
    from jepa_policy.policy import Policy

    checkpoint = _checkpoint(work)
    port, key = _free_port(), "interop-key"
    server = subprocess.Popen([sys.executable, "-m", "jepa_policy.cli", "serve", "--checkpoint", str(checkpoint),
                               "--port", str(port), "--api-key", key, "--threads", "1"],
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
        peer = subprocess.Popen([py, str(PEER), "127.0.0.1", str(port), key], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        metadata = json.loads(str(_recv(peer)["metadata"]))
        result["metadata"] = {k: metadata[k] for k in ("task", "observation", "obs_steps", "action", "control_hz")}
        torch.set_num_threads(1)   # as the server (--threads 1): the same arithmetic order, so equal floats
        policy = Policy.from_checkpoint(checkpoint)
        env = gym.make("JEPA/PushT-v0", image_size=policy.spec.image_size)   # the metadata's observation size
        obs, _ = env.reset(seed=11)
        history, diffs, steps, infer_ms = [], [], 0, []
        success = False
        for t in range(env.spec.max_episode_steps):
            history = (history + [obs])[-policy.obs_steps:]
            stacked = {k: np.stack([h[k] for h in ([history[0]] * (policy.obs_steps - len(history)) + history)])
                       for k in obs}
            _send(peer, step=np.int64(t), **stacked)
            reply = _recv(peer)
            served = reply["action"]
            if reply["infer_ms"] >= 0 and t % policy.n_action_steps == 0:
                infer_ms.append(float(reply["infer_ms"]))
            local = policy.act(obs)
            diffs.append(float(np.abs(served - local).max()))
            obs, _, terminated, truncated, info = env.step(served)
            steps += 1
            success = success or bool(info["is_success"])
            if terminated or truncated:
                break
        _send(peer, done=np.int64(1))
        peer.wait(timeout=30)
        env.close()
        result.update(steps=steps, inferences=int(np.ceil(steps / policy.n_action_steps)), success=success,
                      max_abs_action_diff=max(diffs), bit_equal=max(diffs) == 0.0,
                      median_infer_ms=float(np.median(infer_ms)) if infer_ms else None)
        result["ok"] = result["refused_without_key"] and result["bit_equal"] and steps > 0
    finally:
        server.terminate()
        server.wait(timeout=30)
    return result


def print_openpi(result: dict) -> None:
    meta = result["metadata"]
    print("openpi-client 0.1.2 (WebsocketClientPolicy + ActionChunkBroker) against jepa-policy serve")
    print(f"  metadata: task {meta['task']}, observation {meta['observation']}, chunk {meta['action']['chunk']}")
    print(f"  episode: {result['steps']} steps, {result['inferences']} inferences, success {result['success']}; "
          f"actions vs in-process Policy.act: max |diff| {result['max_abs_action_diff']:.3g} "
          f"({'bit-equal' if result['bit_equal'] else 'DIFFER'}); median server infer {result['median_infer_ms']} ms; "
          f"refused without the API key: {result['refused_without_key']}")
