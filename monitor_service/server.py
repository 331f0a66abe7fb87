"""Run the service in a subprocess on a free loopback port (for tests, the benchmark and the main job)."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx


def free_port(host: str = "127.0.0.1") -> int:
    """A port the OS reports free right now."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


@dataclass
class ServerProcess:
    """A running ``uvicorn`` serving :func:`monitor_service.app.create_app`."""

    url: str
    port: int
    process: subprocess.Popen
    log_path: Path

    def stop(self, timeout: float = 10.0) -> None:
        """Graceful stop (SIGTERM), then SIGKILL if it does not exit in time."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()

    def kill(self) -> None:
        """Hard stop (SIGKILL, as a crash would) of the server's whole process group: with ``workers > 1``
        uvicorn's worker processes would otherwise outlive their killed supervisor."""
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.process.wait(10)

    def __enter__(self) -> ServerProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def start_server(
    database_url: str, *, admin_key: str | None = None, port: int | None = None, workers: int = 1,
    env: dict[str, str] | None = None, log_path: str | Path | None = None, ready_timeout: float = 60.0,
    create: bool = True,
) -> ServerProcess:
    """Start ``jepa-monitor serve`` on 127.0.0.1 and return once /readyz answers 200 (``create``: make a missing
    SQLite database, as tests, the bench and the main job start on a fresh one).

    Settings travel as JEPA_MONITOR_* environment variables (``env`` adds more, e.g. webhook URLs).
    Raises RuntimeError with the server's log tail when it does not become ready.
    """
    port = port or free_port()
    full_env = dict(os.environ)
    full_env["JEPA_MONITOR_DATABASE_URL"] = database_url
    if admin_key:
        full_env["JEPA_MONITOR_ADMIN_KEY"] = admin_key
    full_env.update(env or {})
    log_path = Path(log_path) if log_path else Path(os.environ.get("TMPDIR", "/tmp")) / f"jepa-monitor-{port}.log"
    log = open(log_path, "ab")
    cmd = [sys.executable, "-m", "monitor_service.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
           "--workers", str(workers), "--log-level", "warning"] + (["--create"] if create else [])
    # its own process group, so that ``kill`` reaches uvicorn's worker processes too
    proc = subprocess.Popen(cmd, env=full_env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    log.close()
    server = ServerProcess(f"http://127.0.0.1:{port}", port, proc, log_path)
    deadline = time.monotonic() + ready_timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            break
        try:
            if httpx.get(server.url + "/readyz", timeout=1.0).status_code == 200:
                return server
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    server.kill()
    tail = log_path.read_text(errors="replace")[-3000:]
    raise RuntimeError(f"monitor server did not become ready on port {port}; log {log_path}:\n{tail}")


def provision(url: str, admin_key: str, tasks: dict[str, int | None], robot: str, key_name: str | None = None) -> str:
    """Register ``tasks`` (name -> latent dimension or None) and create a robot key; returns the key's secret.

    The one call a rollout driver needs between :func:`start_server` and :class:`MonitorClient`.
    """
    with httpx.Client(base_url=url, headers={"X-API-Key": admin_key}, timeout=30) as http:
        for name, dim in tasks.items():
            r = http.put(f"/v1/tasks/{name}", json={"latent_dim": dim})
            if r.status_code != 200:
                raise RuntimeError(f"registering task {name!r} failed: {r.status_code} {r.text}")
        r = http.post("/v1/keys", json={"name": key_name or f"{robot}-key", "role": "robot", "robot": robot})
        if r.status_code != 201:
            raise RuntimeError(f"creating the robot key for {robot!r} failed: {r.status_code} {r.text}")
        return r.json()["key"]
