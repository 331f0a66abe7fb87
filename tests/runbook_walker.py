"""Walks a runbook as written: its fenced ``sh`` blocks run in order in one shell state (deploy/RUNBOOK.md for the
monitor, deploy/robot/RUNBOOK.md for the robot bridge)."""
from __future__ import annotations

import re
import socket
import subprocess
from pathlib import Path


def runbook_blocks(text: str) -> list[tuple[str, str]]:
    """(info string, body) of every fenced block, in order; indented blocks (inside list items) included."""
    blocks = []
    for match in re.finditer(r"^( *)```(\w*)\n(.*?)^\1```", text, re.M | re.S):
        indent = len(match.group(1))
        body = "\n".join(line[indent:] for line in match.group(3).splitlines())
        blocks.append((match.group(2), body))
    return blocks


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Shell:
    """Runs blocks one after the other; exported variables and the working folder carry over. ``replace`` maps
    a documented port to the free one this walk uses."""

    def __init__(self, folder: Path, replace: dict[str, str]):
        self.folder, self.replace = folder, replace
        self.state = folder / ".runbook-env"
        self.state.write_text("")

    def run(self, body: str, timeout: float = 180) -> str:
        for old, new in self.replace.items():
            body = body.replace(old, new)
        script = f"set -euo pipefail\nsource {self.state}\n{body}\nexport -p > {self.state}\n"
        out = subprocess.run(["bash", "-c", script], cwd=self.folder, capture_output=True, text=True,
                             timeout=timeout, start_new_session=True)
        assert out.returncode == 0, f"runbook block failed:\n{body}\n--- stdout\n{out.stdout}\n--- stderr\n{out.stderr}"
        return out.stdout

    def env(self, name: str) -> str:
        out = subprocess.run(["bash", "-c", f"source {self.state}; printf %s \"${name}\""], capture_output=True,
                             text=True, check=True)
        return out.stdout
