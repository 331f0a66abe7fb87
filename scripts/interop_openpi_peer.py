"""Runs inside the openpi-client venv (scripts/interop.sh): a robot loop as openpi users write it.

The environment lives in the parent process (this venv has only openpi-client); each step the parent writes the
observation (length-prefixed .npz on stdin) and this loop answers with the action openpi's ActionChunkBroker
takes from WebsocketClientPolicy's chunk. Nothing of this project is imported here.

    python interop_openpi_peer.py HOST PORT API_KEY
"""
import io
import json
import struct
import sys

import numpy as np
from openpi_client import action_chunk_broker, websocket_client_policy


def read() -> dict | None:
    head = sys.stdin.buffer.read(4)
    if len(head) < 4:
        return None
    (n,) = struct.unpack("<I", head)
    data = np.load(io.BytesIO(sys.stdin.buffer.read(n)), allow_pickle=False)
    return {k: data[k] for k in data.files}


def write(**arrays) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    sys.stdout.buffer.write(struct.pack("<I", len(buf.getvalue())) + buf.getvalue())
    sys.stdout.buffer.flush()


def main(host: str, port: str, api_key: str) -> None:
    policy = websocket_client_policy.WebsocketClientPolicy(host, int(port), api_key=api_key)
    metadata = policy.get_server_metadata()
    write(metadata=np.array(json.dumps(metadata)))
    broker = action_chunk_broker.ActionChunkBroker(policy, action_horizon=metadata["action"]["chunk"][0])
    while True:
        msg = read()
        if msg is None or "done" in msg:
            break
        obs = {k: v for k, v in msg.items() if k != "step"}
        obs["step"] = int(msg["step"])
        result = broker.infer(obs)
        write(action=np.asarray(result["actions"]), infer_ms=np.float64(result["server_timing"].get("infer_ms", -1)))


if __name__ == "__main__":
    main(*sys.argv[1:4])
