"""Runs inside the openpi-client venv (scripts/interop.sh): docs/serving.md's robot loop, executed as written there.

The loop is the Python block of the section "Switching a robot loop written for openpi" in docs/serving.md. Only
the server's address and key change (the text's ``"robot-gpu", 8000, api_key="KEY"`` become this script's
arguments); ``robot``, the user's robot in the text, is here the parent process, which owns the environment: each
observation comes on stdin (length-prefixed .npz with ``done`` and ``success``), each action goes back on stdout.
At the end the metadata the loop read goes back too. Nothing of this project is imported here.

    python interop_openpi_peer.py DOC HOST PORT API_KEY EPISODES
"""
import io
import json
import re
import struct
import sys

import numpy as np

SECTION = "## Switching a robot loop written for openpi"
ADDRESS = 'WebsocketClientPolicy("robot-gpu", 8000, api_key="KEY")'


def read() -> dict:
    head = sys.stdin.buffer.read(4)
    if len(head) < 4:
        raise EOFError("the parent closed the pipe")
    (n,) = struct.unpack("<I", head)
    data = np.load(io.BytesIO(sys.stdin.buffer.read(n)), allow_pickle=False)
    return {k: data[k] for k in data.files}


def write(**arrays) -> None:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    sys.stdout.buffer.write(struct.pack("<I", len(buf.getvalue())) + buf.getvalue())
    sys.stdout.buffer.flush()


class Robot:
    """The documented loop's ``robot``: reset() -> obs, step(action) -> (obs, done), succeeded()."""

    def __init__(self):
        self.success = False

    def _next(self) -> tuple[dict, bool]:
        msg = read()
        self.success = bool(msg.pop("success"))
        return msg, bool(msg.pop("done"))

    def reset(self) -> dict:
        return self._next()[0]

    def step(self, action) -> tuple[dict, bool]:
        write(action=np.asarray(action))
        return self._next()

    def succeeded(self) -> bool:
        return self.success


def documented_loop(doc: str) -> str:
    text = open(doc).read()
    block = re.search(r"```python\n(.*?)```", text[text.index(SECTION):], re.S)
    if block is None or ADDRESS not in block.group(1):
        raise SystemExit(f"{doc}: the section {SECTION!r} has no python block that connects with {ADDRESS}")
    return block.group(1).replace(ADDRESS, "WebsocketClientPolicy(HOST, PORT, api_key=API_KEY)")


def main(doc: str, host: str, port: str, api_key: str, episodes: str) -> None:
    namespace = {"HOST": host, "PORT": int(port), "API_KEY": api_key, "n_episodes": int(episodes), "robot": Robot()}
    exec(compile(documented_loop(doc), doc, "exec"), namespace)
    write(metadata=np.array(json.dumps(namespace["meta"])))


if __name__ == "__main__":
    main(*sys.argv[1:6])
