"""Where the bridge listens and who may connect: its configuration, the loopback rule, CurveZMQ, the control socket.

The control socket is a ROUTER with no ZMTP heartbeats (liveness is the bridge's own pings, ``sessions.py``),
a size limit checked by libzmq before the bridge reads a byte (``protocol.MAX_CONTROL_MESSAGE_BYTES``),
``ROUTER_MANDATORY`` so that a reply to a vanished client fails instead of vanishing, and a ZMTP handshake that
must end within ``HANDSHAKE_IVL_MS`` (both sockets: a TCP connection that never greets is dropped, not kept). A
network address is refused without CurveZMQ unless ``insecure_network`` says so (docs/real_robot.md, "Network
security").
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from jepa_robot import protocol as P


HANDSHAKE_IVL_MS = 2000       # a connection's ZMTP handshake must end within this (libzmq's default: 30 s)


@dataclass
class BridgeConfig:
    """Where the bridge listens and what it records."""

    control_address: str = "tcp://127.0.0.1:5555"   # "tcp://127.0.0.1:*" picks a free port
    operator_address: str = "tcp://127.0.0.1:5556"
    record_dir: str | None = None                    # per-episode HDF5 + JSON manifest; None: not written
    chunk_budget: int | None = None                  # None: the task's budget (``bridge.chunk_budget_for``)
    observe_only: bool = False                       # serve observations; refuse every motion
    curve_secret_key: str | None = None              # CurveZMQ: the bridge's key file (jepa-robot-bridge keys)
    curve_authorized_dir: str | None = None          # CurveZMQ: public keys of the clients allowed to connect
    insecure_network: bool = False                   # allow a network bind without CurveZMQ (said explicitly)
    state_file: str | None = None                    # the e-stop latch across restarts (``estop.py``)
    operator_secret_file: str | None = None          # the operator credential (None: operator_secret_file's default)
    start_latched: str | None = None                 # start with the e-stop latched, for this reason (supervisor)
    rt_priority: int | None = None                   # SCHED_FIFO priority of the e-stop path (``realtime_path``)
    # the memory guard's bound (``guard.py``); None: no guard. serve's --max-rss-mb sets it (2048 MiB by default):
    # the bridge's process is its own there, while a bridge embedded in a larger process (tests, a notebook)
    # would measure its host's memory and latch at once
    max_rss_mb: float | None = None


def is_loopback(endpoint: str) -> bool:
    """Whether a ZeroMQ endpoint is reachable from this computer only."""
    host = endpoint.split("://", 1)[-1].rsplit(":", 1)[0]
    return endpoint.startswith(("inproc://", "ipc://")) or P.is_loopback_host(host)


def network_bind_problem(control_address: str, curve: bool, insecure_network: bool) -> str | None:
    """Why a control socket may not bind here: a network address without CurveZMQ, unless said explicitly."""
    if curve or insecure_network or is_loopback(control_address):
        return None
    return (f"the control socket {control_address} would be reachable from the network without encryption: "
            "anyone who can reach it can read the session token and drive the robot; use CurveZMQ "
            "(--curve-keys, or curve_secret_key/curve_authorized_dir in the set-up file), bind 127.0.0.1 and "
            "tunnel over SSH, or pass --insecure-network on a dedicated, isolated robot-policy link "
            "(docs/real_robot.md, 'Network security')")


def operator_bind_problem(operator_address: str, curve: bool) -> str | None:
    """Why the operator socket may not bind here: reachable from the network without CurveZMQ. Anyone who can
    reach it may press the e-stop; only CurveZMQ keeps strangers on the network off it and the operator's
    credential out of sight (there is no --insecure-network for this socket)."""
    if curve or is_loopback(operator_address):
        return None
    return (f"the operator socket {operator_address} would be reachable from the network without CurveZMQ: "
            "anyone who can reach it could press or flood it and read the operator's credential; bind "
            "tcp://127.0.0.1:PORT (operators on the robot computer or over SSH), or configure CurveZMQ "
            "(--curve-keys, or curve_secret_key/curve_authorized_dir in the set-up file) and give each operator "
            "an authorised key (docs/real_robot.md, 'Operator authentication')")


def check_rt_priority(priority: int | None) -> None:
    """Refuse (ValueError naming the fix) a real-time priority this process may not take: tried on the calling
    thread and given back, before any thread of the bridge starts."""
    if priority is None:
        return
    low, high = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
    if not low <= priority <= high:
        raise ValueError(f"--rt-priority must be in [{low}, {high}] (SCHED_FIFO), got {priority}")
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        raise ValueError(f"--rt-priority {priority} needs the right to real-time scheduling (CAP_SYS_NICE, or "
                         "LimitRTPRIO in the systemd unit: deploy/robot/jepa-robot-bridge.service); drop the "
                         "option to run at normal priority") from None
    os.sched_setscheduler(0, before[0], before[1])


def realtime_context(ctx: zmq.Context, priority: int | None) -> None:
    """The context's I/O threads (they read the e-stop's bytes off the socket) at SCHED_FIFO ``priority``; set
    before the first socket starts them."""
    if priority is not None:
        ctx.set(zmq.THREAD_SCHED_POLICY, os.SCHED_FIFO)
        ctx.set(zmq.THREAD_PRIORITY, priority)


def realtime_thread(priority: int | None) -> None:
    """The calling thread at SCHED_FIFO ``priority`` (Linux: pid 0 is the calling thread)."""
    if priority is not None:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))


# the bridge's ZeroMQ context has two I/O threads: the control socket's connections use the first, the operator
# socket's the second, so a flood of connections on one socket never queues the other's bytes (the e-stop's)
IO_THREADS = 2
CONTROL_IO_AFFINITY, OPERATOR_IO_AFFINITY = 1, 2


def open_control_socket(ctx: zmq.Context, config: BridgeConfig) -> tuple[zmq.Socket, ThreadAuthenticator | None]:
    """The bound control ROUTER and, with CurveZMQ, the authenticator that admits the authorised clients."""
    sock = ctx.socket(zmq.ROUTER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.ROUTER_MANDATORY, 1)
    sock.setsockopt(zmq.MAXMSGSIZE, P.MAX_CONTROL_MESSAGE_BYTES)
    sock.setsockopt(zmq.AFFINITY, CONTROL_IO_AFFINITY)   # its connections' I/O never shares the operator's thread
    sock.setsockopt(zmq.HANDSHAKE_IVL, HANDSHAKE_IVL_MS)  # a raw TCP connection that never greets is dropped
    auth = None
    try:
        auth = _setup_curve(ctx, sock, config)
        sock.bind(config.control_address)
    except (zmq.ZMQError, ValueError, RuntimeError):
        if auth is not None:
            auth.stop()
        sock.close(linger=0)
        raise
    return sock, auth


def _setup_curve(ctx: zmq.Context, sock: zmq.Socket, config: BridgeConfig) -> ThreadAuthenticator | None:
    if config.curve_secret_key is None:
        return None
    if not zmq.has("curve"):
        raise RuntimeError("this libzmq has no CURVE support; install pyzmq's wheels (they include it)")
    public, secret = zmq.auth.load_certificate(config.curve_secret_key)
    if secret is None:
        raise ValueError(f"{config.curve_secret_key} holds no secret key; pass the bridge's '.key_secret' file "
                         "made by `jepa-robot-bridge keys`")
    authorized = config.curve_authorized_dir
    if not authorized or not Path(authorized).is_dir():
        raise ValueError("CurveZMQ needs curve_authorized_dir: a folder with the public key of every client "
                         "allowed to connect (`jepa-robot-bridge keys` writes one)")
    auth = ThreadAuthenticator(ctx)
    auth.start()
    auth.configure_curve(domain="*", location=str(authorized))
    sock.curve_secretkey, sock.curve_publickey, sock.curve_server = secret, public, True
    return auth


def operator_curve(config: BridgeConfig, sock: zmq.Socket) -> None:
    """A network-reachable operator socket speaks CurveZMQ with the bridge's keys (the authenticator the control
    socket started admits the authorised keys); a loopback one stays open to the robot computer's processes."""
    if is_loopback(config.operator_address) or config.curve_secret_key is None:
        return
    public, secret = zmq.auth.load_certificate(config.curve_secret_key)
    sock.curve_secretkey, sock.curve_publickey, sock.curve_server = secret, public, True
