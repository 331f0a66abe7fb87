"""The policy server's settings, checked before any checkpoint is loaded, and its secrets read from the
environment or a file (never only from argv, which every local user reads in ``ps``)."""
from __future__ import annotations

import os
import stat
import sys
from dataclasses import dataclass
from pathlib import Path

from jepa_robot.protocol import is_loopback_host

MONITOR_BUFFER = 100_000
API_KEY_ENV = "JEPA_POLICY_API_KEY"
MONITOR_KEY_ENV = "JEPA_POLICY_MONITOR_KEY"


@dataclass
class ServeConfig:
    host: str = "127.0.0.1"
    port: int = 8000
    api_key: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    tls_client_ca: str | None = None    # mutual TLS: clients must show a certificate this CA signed
    max_batch: int = 16
    max_queue: int = 64
    max_connections: int = 32
    idle_evict_s: float = 5.0           # at the cap, a connection idle longer than this makes room for a new one
    monitor_url: str | None = None
    monitor_key: str | None = None
    task_id: str | None = None          # the monitor's task name (default: the checkpoint's task)
    robot: str | None = None            # the monitor key's robot
    monitor_buffer: int = MONITOR_BUFFER
    monitor_flush_s: float = 10.0       # on stop, how long buffered records may take to reach the monitor
    monitor_scores: tuple[str, ...] | None = ()   # named failure scores sent with each decision: () none, None all


def check_config(config: ServeConfig) -> None:
    """Refuse a configuration that cannot serve safely, before any checkpoint is loaded."""
    if (config.tls_cert is None) != (config.tls_key is None):
        raise ValueError("TLS needs both --tls-cert and --tls-key")
    if config.tls_client_ca and not config.tls_cert:
        raise ValueError("--tls-client-ca (mutual TLS) needs the server's own --tls-cert/--tls-key")
    if config.api_key is not None and not config.api_key.strip():
        raise ValueError(f"the API key is blank (only whitespace); set {API_KEY_ENV} (or --api-key-file) to the key "
                         "clients send, or unset it on loopback")
    if not is_loopback_host(config.host) and not (config.api_key or config.tls_client_ca):
        # TLS alone encrypts but lets anyone in: a client needs a key or a certificate of ours
        raise ValueError(f"--host {config.host} is reachable from the network: pass --api-key KEY (or "
                         f"{API_KEY_ENV} / --api-key-file; clients send 'Authorization: Api-Key KEY', "
                         "openpi-client's api_key), or mutual TLS (--tls-cert/--tls-key with --tls-client-ca: "
                         "clients must show a certificate that CA signed); a policy server drives robots")
    if config.monitor_url and not config.monitor_key:
        raise ValueError(f"--monitor-url needs --monitor-key (or {MONITOR_KEY_ENV} / --monitor-key-file: a robot key "
                         "of the monitor service)")
    if config.max_batch < 1 or config.max_queue < 1 or config.max_connections < 1:
        raise ValueError("--max-batch, --max-queue and --max-connections must be >= 1")
    if not (isinstance(config.idle_evict_s, (int, float)) and 0 < config.idle_evict_s < float("inf")):
        raise ValueError(f"idle_evict_s must be a number of seconds > 0, not {config.idle_evict_s!r}")


def read_secret(flag: str, value: str | None, file: str | None, env: str) -> str | None:
    """A secret from ``--flag VALUE``, ``--flag-file PATH`` (its first line) or the environment variable ``env``,
    in that order; giving both the flag and the file is refused, and a secret on argv is warned about on stderr."""
    if value is not None and file is not None:
        raise ValueError(f"pass {flag} or {flag}-file, not both")
    if file is not None:
        path = Path(file)
        if path.is_dir():
            raise ValueError(f"{flag}-file {file} is a directory; give the file that holds the key (chmod 600)")
        if not path.is_file():
            raise FileNotFoundError(f"{flag}-file {file} does not exist; write the key into it (chmod 600)")
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except UnicodeDecodeError:
            raise ValueError(f"{flag}-file {file} is not UTF-8 text; write the key on its first line as text"
                             ) from None
        secret = lines[0].strip() if lines else ""
        if not secret:
            raise ValueError(f"{flag}-file {file} is empty; write the key on its first line")
        if path.stat().st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise ValueError(f"{flag}-file {file} is readable by other users; chmod 600 {file}")
        return secret
    if value is not None:
        print(argv_secret_warning(flag, env), file=sys.stderr)
        return value
    secret = os.environ.get(env)
    if secret is not None and secret and not secret.strip():
        raise ValueError(f"{env} is blank (only whitespace); set it to the key, or unset it")
    return secret or None


def argv_secret_warning(flag: str, env: str) -> str:
    """What a secret given on the command line is told: who can read it, and the two ways that hide it."""
    return (f"warning: {flag} on the command line is visible to every local user (ps, /proc/<pid>/cmdline); set "
            f"{env} or pass {flag}-file PATH (a file of mode 600) instead")
