"""``jepa-robot-bridge bench --load``: the bridge under local load, every party in a process of its own.

A simulated PushT bridge (``serve --backend sim``, link liveness on: the default link timeout of one control
period) serves a policy process that runs action chunks back to back, as fast as the simulator allows (the
bridge's loop is never idle, the worst case for draining its sockets). With ``--realtime`` the bridge paces
actions at the task's 10 Hz, as on the robot: the chunk rate then shows whether the flood starves the
controller, not how much CPU the flood's process takes from it on a small machine. ``--nice -10`` runs the
bridges at the priority the systemd unit gives them (negative values need root). The scenarios:

* ``flood``: a stranger process with four DEALER sockets sends undecodable and tokenless frames at full speed on
  the control socket and reads the replies. Measured: the e-stop, and the controller's chunk rate under the
  flood over its rate alone (the same length of time just before).
* ``operators``: 50 operator connections each keep a ``status`` queued (each sends the next on its answer).
* ``operators+flood``: both at once (an e-stop queued behind other operators' commands on a flooded bridge).
* ``flood-elsewhere``: the same flood at a second bridge on this machine: the CPU it takes, without touching
  the controller's bridge. Its rate ratio is what the machine allows; ``flood``'s beside it is what the bridge
  adds.
* ``big``: a stranger keeps sending a 16 MiB message that is slow to decode (16 M one-byte integers).
* ``many-strangers``: 300 DEALER connections on the control socket, each sending 16,000-byte msgpack arrays
  (slow to decode, under the stranger size limit) as fast as they go and reading the replies.
* ``operator-flood``: the same with 300 connections on the operator socket and 3,995-byte arrays (under its
  4 KiB limit).
* ``cpu``, ``cpu+flood``: twice the cores' worth of busy processes (and the flood): the e-stop under CPU
  overload, with ``--nice``, ``--rt-priority`` (the e-stop path at SCHED_FIFO) or ``--process-fifo``.
* ``estop-junk``, ``estop-junk-64``: 60-byte frames that contain ``estop`` but are none, at full speed from one
  operator connection (64), for ``--flood-seconds``: whether ``status`` is answered during the flood (with and
  without the operator's credential) and how soon after it.
* ``held``, ``held+flood``: ``--trials`` e-stops, each at a random moment of a running chunk, on an instrumented
  bridge in this process (safety check slowed by ``--check-ms``; a stranger flooding the control socket): the
  actions that started after a held answer (``held_presses``).
* ``aborts``: ``--abort-runs`` fresh bridges, each with a controller, flooded for ``--flood-seconds``; counts the
  bridges that died (libzmq's ``!_io_error`` abort is exit -6) and the controller links held or lost meanwhile.

E-stop: the operator's ``OperatorClient.estop`` timed from send to answer, ``--trials`` times per scenario, each
followed by ``clear_estop`` (the controller starts a new episode). ``latched`` is the bridge's own clock at the
latch (its ``latched_at``) minus the send time, where the bridge reports it. Prints p50 / max per scenario.

One module of about 700 lines on purpose: the scenarios' parties run as child processes of this same module
(``python -m jepa_robot.load_bench ROLE ADDRESS``), so the roles, the scenarios that start them and the report
that reads them share one file.
"""
from __future__ import annotations

import collections
import json
import os
import random
import resource
import subprocess
import sys
import threading
import time

import msgpack
import numpy as np
import zmq
from tqdm import tqdm

from jepa_robot import protocol as P
from jepa_robot.backends.sim import SimBackend
from jepa_robot.bridge import BridgeConfig, RobotBridge
from jepa_envs.real_robot.proxy import BridgeError, RealRobotEnv
from jepa_robot.safety import SafetyConfig
from jepa_robot.operator import OperatorClient, OperatorError

FLOOD_SOCKETS = 4
FLOOD_HEARTBEATS = "JEPA_FLOOD_ZMTP_HEARTBEATS"   # set: the flood's sockets send ZMTP heartbeats of their own
OPERATOR_CONNECTIONS = 50
BIG_MESSAGE = msgpack.packb([1] * (16 * 1024 * 1024 - 16))   # 16 MiB of one-byte integers: slow to decode
# each scenario's load processes (``aborts`` is its own loop of fresh bridges)
MANY_CONNECTIONS = 300
# slow to decode and within the size limits: 15,990 one-byte integers (control: under the stranger limit of 16 KiB)
# and 3,990 (operator: under its 4 KiB limit)
STRANGER_JUNK = b"\xdd" + (15990).to_bytes(4, "big") + b"\x01" * 15990
OPERATOR_JUNK = b"\xdd" + (3990).to_bytes(4, "big") + b"\x01" * 3990
LOADS = {"flood": ["flood"], "operators": ["operators"], "operators+flood": ["operators", "flood"], "big": ["big"],
         "flood-elsewhere": ["flood"], "many-strangers": ["strangers"], "operator-flood": ["opflood"],
         # twice the cores' worth of busy processes: the CPU overload the e-stop's bound is stated under
         "cpu": ["spin"] * (2 * (os.cpu_count() or 1)), "cpu+flood": ["spin"] * (2 * (os.cpu_count() or 1)) + ["flood"]}
# the operator socket flooded with e-stop-like junk (one socket, 64): is the operator ever silenced?
SILENCE = {"estop-junk": "estopjunk", "estop-junk-64": "estopjunk64"}
SCENARIOS = (*LOADS, *SILENCE, "held", "held+flood", "aborts")


# ----------------------------------------------------------------------------- the load, one process each
def _until_stdin_closes() -> threading.Event:
    stop = threading.Event()

    def watch() -> None:
        sys.stdin.read()
        stop.set()
    threading.Thread(target=watch, daemon=True).start()
    return stop


def run_flood(address: str, sockets: int = FLOOD_SOCKETS) -> None:
    """Undecodable bytes and tokenless requests at full speed on ``sockets`` DEALER connections."""
    stop = _until_stdin_closes()
    ctx = zmq.Context()
    frames = [b"\xc1\xc1 not msgpack \xc1", P.encode({"type": P.STEP, "seq": 7, "action": [1.0, 2.0]}),
              P.encode({"type": P.CHUNK, "seq": 9, "session": "0" * 32, "actions": [[1.0, 2.0]] * 8})]
    socks = []
    for _ in range(sockets):
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        if os.environ.get(FLOOD_HEARTBEATS):   # the stranger's own ZMTP heartbeats: PINGs inside its flood
            sock.setsockopt(zmq.HEARTBEAT_IVL, 10)
            sock.setsockopt(zmq.HEARTBEAT_TTL, 1000)
            sock.setsockopt(zmq.HEARTBEAT_TIMEOUT, 1000)
        sock.connect(address)
        socks.append(sock)
    print(json.dumps({"ready": True}), flush=True)   # connected: the flood starts now (Child.wait_ready)
    sent = received = 0
    while not stop.is_set():
        for sock in socks:
            for frame in frames:
                try:
                    sock.send(frame, zmq.NOBLOCK)
                    sent += 1
                except zmq.Again:
                    pass
            received += _read_replies(sock, 8)
    _report_and_close(ctx, socks, sent, received)


def _read_replies(sock: zmq.Socket, most: int) -> int:
    """Up to ``most`` waiting replies read and dropped; how many there were."""
    for n in range(most):
        try:
            sock.recv(zmq.NOBLOCK)
        except zmq.Again:
            return n
    return most


def _report_and_close(ctx: zmq.Context, socks: list, sent: int, received: int) -> None:
    print(json.dumps({"sent": sent, "received": received}), flush=True)
    for sock in socks:
        sock.close(linger=0)
    ctx.term()


def run_many(address: str, payload: bytes, connections: int = MANY_CONNECTIONS) -> None:
    """``connections`` DEALER sockets, each sending ``payload`` as fast as its pipe takes it and reading replies."""
    stop = _until_stdin_closes()
    ctx = zmq.Context()
    socks = []
    for _ in range(connections):
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.SNDHWM, 1000)
        sock.connect(address)
        socks.append(sock)
    print(json.dumps({"ready": True}), flush=True)   # connected: the flood starts now (Child.wait_ready)
    sent = received = 0
    while not stop.is_set():
        for sock in socks:
            for _ in range(4):
                try:
                    sock.send(payload, zmq.NOBLOCK)
                    sent += 1
                except zmq.Again:
                    break
            received += _read_replies(sock, 16)
    _report_and_close(ctx, socks, sent, received)


def run_operators(address: str, connections: int = OPERATOR_CONNECTIONS) -> None:
    """``connections`` REQ sockets, each with one ``status`` always queued."""
    stop = _until_stdin_closes()
    ctx = zmq.Context()
    poller = zmq.Poller()
    request = msgpack.packb({"v": P.PROTOCOL_VERSION, "type": P.OP_STATUS})
    socks = []
    for _ in range(connections):
        sock = ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(address)
        sock.send(request)
        poller.register(sock, zmq.POLLIN)
        socks.append(sock)
    answered = 0
    while not stop.is_set():
        for sock, _ in poller.poll(100):
            sock.recv()
            answered += 1
            sock.send(request)
    print(json.dumps({"answered": answered}), flush=True)
    for sock in socks:
        sock.close(linger=0)
    ctx.term()


def run_status_flood(address: str, connections: int = MANY_CONNECTIONS, in_flight: int = 4) -> None:
    """``connections`` DEALER sockets without the credential, each keeping ``in_flight`` valid ``status`` requests
    waiting (the next sent as an answer comes): the event loop's queue of operator commands stays full."""
    stop = _until_stdin_closes()
    ctx = zmq.Context()
    ctx.MAX_SOCKETS = connections + 64
    request = [b"", msgpack.packb({"v": P.PROTOCOL_VERSION, "type": P.OP_STATUS})]
    poller, socks = zmq.Poller(), []
    for _ in range(connections):
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(address)
        for _ in range(in_flight):
            sock.send_multipart(request)
        poller.register(sock, zmq.POLLIN)
        socks.append(sock)
    print(json.dumps({"ready": True}), flush=True)
    answers: collections.Counter = collections.Counter()
    while not stop.is_set():
        for sock, _ in poller.poll(50):
            reply = msgpack.unpackb(sock.recv_multipart()[-1], raw=False)
            answers[reply.get("code") or reply.get("type")] += 1
            sock.send_multipart(request)
    print(json.dumps({"answers": dict(answers)}), flush=True)
    for sock in socks:
        sock.close(linger=0)
    ctx.term()


def run_big(address: str) -> None:
    """A stranger that keeps one 16 MiB slow-to-decode message in flight."""
    stop = _until_stdin_closes()
    ctx = zmq.Context()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(address)
    sent = 0
    while not stop.is_set():
        sock.send(BIG_MESSAGE)
        sent += 1
        if not sock.poll(2000):   # a bridge that drops it unread (size limit) answers nothing
            sock.close(linger=0)
            sock = ctx.socket(zmq.DEALER)
            sock.setsockopt(zmq.LINGER, 0)
            sock.connect(address)
            continue
        sock.recv()
    print(json.dumps({"sent": sent}), flush=True)
    sock.close(linger=0)
    ctx.term()


def run_controller(address: str) -> None:
    """A policy process: episodes of 8-action chunks back to back; prints each chunk's wall-clock end."""
    stop = _until_stdin_closes()
    env = RealRobotEnv(address=address, client_name="controller", timeout_s=30.0)
    print(json.dumps({"ready": True}), flush=True)
    done, errors = [], {}
    obs = None
    while not stop.is_set():
        try:
            if obs is None:
                obs, _ = env.reset()
            obs, _, terminated, truncated, _ = env.step_chunk(np.tile(obs["agent_pos"], (8, 1)))
            done.append(time.time())
            if terminated or truncated:
                obs = None
        except (BridgeError, TimeoutError) as exc:   # e-stop latched: wait for the operator's clear
            errors[type(exc).__name__] = errors.get(type(exc).__name__, 0) + 1
            obs = None
            time.sleep(0.02)
    print(json.dumps({"chunks": done, "errors": errors}), flush=True)
    env.close()


# 60 bytes that contain "estop" but are no e-stop: once decoded for free and charged to nothing
ESTOP_LIKE_JUNK = b"\x81\xa4type\xa5estop" + b"\xc1" * 48


def run_estop_junk(address: str, connections: int = 1) -> None:
    """E-stop-like junk on the operator socket at full speed from ``connections`` DEALER sockets."""
    run_many(address, ESTOP_LIKE_JUNK, connections)


def operator_silence(operator: str, flood: "Child", flood_s: float, every_s: float = 0.1,
                     timeout_s: float = 2.0, secret_file: str | None = None) -> dict:
    """While ``flood`` runs for ``flood_s`` seconds: a ``status`` every ``every_s`` from a new connection without
    the operator's credential and the operator's authenticated ``clear_estop`` (nothing latched: it changes
    nothing), each answered or not within ``timeout_s``; then the flood stops and ``status`` is asked (1 s timeout
    each) until answered. Latencies in ms; answers by kind."""
    def ask(authenticated: bool, timeout: float) -> tuple[str, float]:
        t0 = time.perf_counter()
        try:
            with OperatorClient(operator, timeout_s=timeout, secret_file=secret_file if authenticated
                                else "/nonexistent/operator.secret") as op:
                op.clear_estop() if authenticated else op.status()
            kind = "result"
        except OperatorError as exc:
            kind = exc.code or "error"
        except TimeoutError:
            kind = "silence"
        return kind, (time.perf_counter() - t0) * 1e3

    during: dict[str, list] = {"open": [], "operator": []}
    flood.wait_ready()
    end = time.monotonic() + flood_s
    while time.monotonic() < end:
        during["open"].append(ask(False, timeout_s))
        during["operator"].append(ask(True, timeout_s))
        time.sleep(every_s)
    flood.finish()
    stopped, after = time.perf_counter(), []
    while time.perf_counter() - stopped < 30:
        kind, ms = ask(False, 1.0)
        after.append((kind, ms))
        if kind == "result":
            break
    return {"during": {who: {"answers": dict(collections.Counter(k for k, _ in xs)),
                             "max_ms": max((ms for _, ms in xs), default=None)} for who, xs in during.items()},
            "after_flood_first_answer_ms": (time.perf_counter() - stopped) * 1e3 if after[-1][0] == "result"
            else None, "after_flood_tries": len(after)}


class EventLog:
    """Events in one total order (a counter under a lock), whatever thread logs them."""

    def __init__(self):
        self._lock = threading.Lock()
        self._order = 0
        self.events: list[tuple[int, str]] = []

    def add(self, kind: str) -> None:
        with self._lock:
            self._order += 1
            self.events.append((self._order, kind))


def instrument(bridge, log: EventLog, check_s: float = 0.0) -> None:
    """Log every action's start and end and every emergency stop of ``bridge``'s backend; slow its safety check
    down by ``check_s`` (a real robot's checks may take milliseconds)."""
    backend, guard = bridge.backend, bridge.guard
    apply, stop, check = backend.apply, backend.emergency_stop, guard.check

    def logged_apply(action):
        log.add("start")
        try:
            return apply(action)
        finally:
            log.add("end")

    def logged_stop():
        log.add("stop")
        stop()

    def slow_check(*args):
        if check_s:
            time.sleep(check_s)
        return check(*args)
    backend.apply, backend.emergency_stop, guard.check = logged_apply, logged_stop, slow_check


def hold_violations(events: list[tuple[int, str]]) -> list[str]:
    """Every action started between a held answer ("answered") and the next "cleared"; every stop sent while an
    action was inside apply."""
    problems, answered, running = [], False, 0
    for order, kind in events:
        if kind == "start":
            running += 1
            if answered:
                problems.append(f"an action started at {order}, after a held answer")
        elif kind == "end":
            running -= 1
        elif kind == "stop" and running:
            problems.append(f"the stop at {order} went out while an action was inside apply")
        elif kind == "answered":
            answered = True
        elif kind == "cleared":
            answered = False
    return problems


def held_presses(presses: int, check_s: float = 0.0, flood: bool = False, seed: int = 0) -> dict:
    """``presses`` e-stops, each at a random moment of a running chunk, on an instrumented sim bridge in this
    process (with a stranger flooding its control socket from another process when ``flood``); each answer
    logged in the same order as the backend's calls, then cleared. The actions started after a held answer."""
    config = BridgeConfig("tcp://127.0.0.1:*", "tcp://127.0.0.1:*", chunk_budget=10**6)
    bridge = RobotBridge(SimBackend("PushT"), SafetyConfig(link_timeout_s=2.0, command_deadline_s=60.0), config)
    bridge.start()
    log = EventLog()
    instrument(bridge, log, check_s)
    rng = random.Random(seed)
    env = RealRobotEnv(address=bridge.control_endpoint, client_name="controller", timeout_s=30.0)
    op = OperatorClient(bridge.operator_endpoint, timeout_s=10.0)
    stranger = Child("flood", bridge.control_endpoint) if flood else None
    answers, mid_chunk = [], 0
    try:
        if stranger is not None:
            stranger.wait_ready()
        for _ in range(presses):
            obs, _ = env.reset(seed=rng.randrange(2**31))
            runner = threading.Thread(target=env.step_chunk, args=(np.tile(obs["agent_pos"], (8, 1)),))
            runner.start()
            time.sleep(rng.uniform(0.0, 0.01 + 8 * check_s))
            mid_chunk += bridge.runner.executing
            t0 = time.perf_counter()
            op.estop()
            answers.append((time.perf_counter() - t0) * 1e3)
            log.add("answered")
            runner.join(timeout=30)
            op.clear_estop()
            log.add("cleared")
    finally:
        if stranger is not None:
            stranger.finish()
        op.close()
        env.close()
        bridge.close()
    problems = hold_violations(log.events)
    x = np.asarray(answers)
    return {"presses": presses, "check_ms": check_s * 1e3, "flood": flood, "mid_chunk": mid_chunk,
            "actions_after_held_answer": sum("after a held answer" in p for p in problems),
            "stops_during_apply": sum("while an action" in p for p in problems),
            "answer_ms": {"p50": float(np.median(x)), "p99": float(np.percentile(x, 99)), "max": float(x.max())}}


def run_spin(address: str) -> None:
    """One core's worth of CPU load (a busy loop) until stdin closes; ``address`` is not used."""
    stop = _until_stdin_closes()
    print(json.dumps({"ready": True}), flush=True)
    spins = 0
    while not stop.is_set():
        for _ in range(10_000):
            spins += 1
    print(json.dumps({"spins": spins}), flush=True)


ROLES = {"flood": run_flood, "spin": run_spin, "estopjunk": run_estop_junk,
         "estopjunk64": lambda address: run_estop_junk(address, 64), "operators": run_operators, "big": run_big,
         "controller": run_controller,
         "strangers": lambda address: run_many(address, STRANGER_JUNK), "statusflood": run_status_flood,
         "opflood": lambda address: run_many(address, OPERATOR_JUNK)}


# ----------------------------------------------------------------------------- the stack under test
class Child:
    """A role of this module in a process of its own; ``finish`` closes its stdin and reads its last line."""

    def __init__(self, role: str, address: str):
        self.proc = subprocess.Popen([sys.executable, "-m", "jepa_robot.load_bench", role, address],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def wait_ready(self) -> None:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the load process ended before it was ready (exit {self.proc.poll()})")

    def finish(self, timeout: float = 60.0) -> dict:
        try:
            self.proc.stdin.close()
            out = self.proc.stdout.read()
            self.proc.wait(timeout=timeout)
        except (subprocess.TimeoutExpired, BrokenPipeError):
            self.proc.kill()
            self.proc.wait()
            return {}
        lines = [line for line in out.splitlines() if line.startswith("{")]
        return json.loads(lines[-1]) if lines else {}


class Bridge:
    """A sim bridge in a child process on free loopback ports (heartbeats on: the default link timeout)."""

    def __init__(self, extra: tuple[str, ...] = (), nice: int = 0, rt_priority: int | None = None,
                 process_fifo: int | None = None, descriptors: int | None = None):
        """``extra``: more serve arguments, e.g. ("--realtime",); ``nice``: the process's niceness (the systemd
        unit's Nice=-10); ``rt_priority``: the e-stop path at SCHED_FIFO (serve --rt-priority);
        ``process_fifo``: every thread of the bridge at SCHED_FIFO (chrt), for comparison; ``descriptors``: the
        bridge's RLIMIT_NOFILE (the unit's LimitNOFILE)."""
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        priority = ["nice", "-n", str(nice)] if nice else []
        if process_fifo is not None:
            priority = ["chrt", "-f", str(process_fifo)]
        if rt_priority is not None:
            extra = (*extra, "--rt-priority", str(rt_priority))
        self.proc = subprocess.Popen(
            [*priority, sys.executable, "-m", "jepa_robot.cli", "serve", "--backend", "sim", "--task", "PushT",
             "--chunk-budget", "1000000", "--bind", "tcp://127.0.0.1:*", "--operator-bind", "tcp://127.0.0.1:*",
             "--no-prompt", *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
            preexec_fn=None if descriptors is None else lambda: resource.setrlimit(resource.RLIMIT_NOFILE,
                                                                                   (descriptors, descriptors)))
        banner = self.proc.stdout.readline()
        if " on " not in banner:
            raise RuntimeError(f"the bridge did not start: {banner!r} {self.proc.stderr.read()[-2000:]}")
        self.control = banner.split(" on ")[1].split(",")[0].strip()
        self.operator = banner.rsplit("operator socket ", 1)[1].split()[0].strip()
        self._stderr: list[str] = []
        threading.Thread(target=lambda: self._stderr.extend(self.proc.stderr), daemon=True).start()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def abort_line(self) -> str:
        return next((line.strip() for line in self._stderr if "Assertion failed" in line), "")

    def status(self) -> dict:
        with OperatorClient(self.operator, timeout_s=10.0) as op:
            return op.status()

    def close(self) -> int:
        if self.alive():
            try:
                with OperatorClient(self.operator, timeout_s=5.0) as op:
                    op.shutdown()
                self.proc.wait(timeout=20)
            except (TimeoutError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


def _wait_for_chunks(controller_started: float, seconds: float) -> None:
    time.sleep(max(0.0, controller_started + seconds - time.time()))


def time_estops(operator: str, trials: int, seed: int = 0) -> dict:
    """``trials`` e-stops, each answered (or timed out) then cleared; latencies in ms."""
    rng = random.Random(seed)
    answer, latched, unacknowledged, failures = [], [], 0, 0
    op = OperatorClient(operator, timeout_s=5.0)
    try:
        for _ in range(trials):
            time.sleep(rng.uniform(0.15, 0.35))   # mid-chunk, at a random phase
            sent_wall, t0 = time.time(), time.perf_counter()
            try:
                status = op.estop()
            except (TimeoutError, OperatorError, zmq.ZMQError) as exc:
                failures += 1
                answer.append(float("inf"))
                op.close()
                op = OperatorClient(operator, timeout_s=5.0)   # a REQ socket after a timeout is stuck
                print(f"  e-stop failed: {type(exc).__name__}: {exc}", file=sys.stderr)
                continue
            answer.append((time.perf_counter() - t0) * 1e3)
            if status.get("latched_at") is not None:
                latched.append((status["latched_at"] - sent_wall) * 1e3)
            if status.get("acknowledged") is False:
                unacknowledged += 1
            for _ in range(3):
                try:
                    op.clear_estop()
                    break
                except (TimeoutError, OperatorError, zmq.ZMQError):
                    op.close()
                    op = OperatorClient(operator, timeout_s=5.0)
    finally:
        op.close()
    return {"trials": trials, "answer_ms": answer, "latched_ms": latched, "unacknowledged": unacknowledged,
            "failures": failures}


def _summary(samples: list[float]) -> dict:
    x = np.asarray(samples, np.float64)
    if not x.size:
        return {"p50_ms": None, "p99_ms": None, "max_ms": None, "over_100ms": 0}
    return {"p50_ms": float(np.median(x)), "p99_ms": float(np.percentile(x, 99)), "max_ms": float(x.max()),
            "over_100ms": int((x > 100).sum())}


def scenario(name: str, trials: int, window_s: float, realtime: bool = False, nice: int = 0,
             rt_priority: int | None = None, process_fifo: int | None = None) -> dict:
    """One load scenario on a fresh bridge with a controller: chunk rates and the e-stop under that load."""
    bridge = Bridge(("--realtime",) if realtime else (), nice, rt_priority, process_fifo)
    other = Bridge(nice=nice, rt_priority=rt_priority) if name == "flood-elsewhere" else None
    controller = Child("controller", bridge.control)
    controller.wait_ready()
    loads: list[Child] = []
    out: dict = {"scenario": name}
    try:
        started = time.time()
        time.sleep(window_s)   # the controller alone
        alone = (started, time.time())
        target = other or bridge
        for role in LOADS[name]:
            loads.append(Child(role, target.operator if role in ("operators", "opflood") else target.control))
            if role in ("flood", "spin"):   # a loaded machine can take seconds to start it: time from its start
                loads[-1].wait_ready()
        time.sleep(0.3)
        loaded_from = time.time()
        time.sleep(window_s)   # the controller under the load
        loaded = (loaded_from, time.time())
        out["estop"] = time_estops(bridge.operator, trials) if bridge.alive() else {
            "trials": trials, "answer_ms": [], "latched_ms": [], "unacknowledged": 0, "failures": trials}
        out["load"] = [child.finish() for child in loads]
        loads = []
        out["bridge_alive"] = bridge.alive()
        out["abort"] = bridge.abort_line()
        status = bridge.status() if bridge.alive() else {"events": [], "counters": {}}
        out["link_events"] = [e["kind"] for e in status["events"] if e["kind"].startswith("link")]
        out["counters"] = status["counters"]
    finally:
        for child in loads:
            child.finish()
        result = controller.finish()
        bridge.close()
        if other is not None:
            other.close()
    chunks = np.asarray(result.get("chunks", []), np.float64)
    rates = [float(((chunks >= a) & (chunks < b)).sum() / (b - a)) for a, b in (alone, loaded)]
    out["chunks_per_s_alone"], out["chunks_per_s_loaded"] = rates
    out["rate_ratio"] = rates[1] / rates[0] if rates[0] else None
    out["controller_errors"] = result.get("errors", {})
    return out


def abort_runs(runs: int, flood_seconds: float, nice: int = 0, rt_priority: int | None = None) -> dict:
    """``runs`` fresh bridges flooded with a controller running; which died, which lost the controller's link."""
    died, lost_link, lines = 0, 0, []
    for run in range(runs):
        state = "alive"
        bridge = Bridge(nice=nice, rt_priority=rt_priority)
        controller = Child("controller", bridge.control)
        controller.wait_ready()
        try:
            time.sleep(0.5)
            flood = Child("flood", bridge.control)
            flood.wait_ready()
            time.sleep(flood_seconds)
            flood.finish()
            time.sleep(0.5)   # the flood's connections close: libzmq's abort came here
            if bridge.alive():
                status = bridge.status()
                if any(e["kind"].startswith("link") for e in status["events"]):
                    lost_link += 1
                    state = "alive, the controller's link was held or lost"
            else:
                died += 1
                state = f"DIED (exit {bridge.proc.returncode}: {bridge.abort_line()})"
                lines.append(f"run {run + 1}: exit {bridge.proc.returncode}: {bridge.abort_line()}")
        finally:
            controller.finish()
            bridge.close()
        print(f"  run {run + 1}/{runs}: {state}", flush=True)
    return {"runs": runs, "aborts": died, "controller_link_lost_or_held": lost_link, "abort_lines": lines}


def run_load_bench(args) -> int:
    """Run the scenarios named by ``args.load`` and print their numbers (see the module docstring)."""
    names = [n.strip() for n in args.load.split(",") if n.strip()]
    unknown = sorted(set(names) - set(SCENARIOS))
    if unknown:
        raise SystemExit(f"error: unknown load scenario(s) {unknown}; choose from {', '.join(SCENARIOS)}")
    with open("/proc/loadavg") as f:
        load = f.read().split()[:3]
    print(f"load average before: {' '.join(load)} ({os.cpu_count()} CPUs); libzmq {zmq.zmq_version()}, "
          f"pyzmq {zmq.__version__}; bridge {'at 10 Hz' if args.realtime else 'as fast as it runs'}, "
          f"niceness {args.nice}, e-stop path "
          f"{'SCHED_FIFO ' + str(args.rt_priority) if args.rt_priority else 'at normal priority'}"
          + (f", the whole bridge at SCHED_FIFO {args.process_fifo}" if args.process_fifo else ""),
          flush=True)
    results = {"loadavg": load, "libzmq": zmq.zmq_version(), "pyzmq": zmq.__version__}
    bar = tqdm(names, desc="load scenarios", unit="scenario", disable=args.no_progress, file=sys.stderr)
    for name in bar:
        bar.set_postfix_str(name)
        if name in SILENCE:
            bridge = Bridge(nice=args.nice, rt_priority=args.rt_priority, process_fifo=args.process_fifo)
            try:
                results[name] = r = operator_silence(bridge.operator, Child(SILENCE[name], bridge.operator),
                                                     args.flood_seconds)
            finally:
                bridge.close()
            print(f"{name}: during a {args.flood_seconds:g} s flood, status without the credential "
                  f"{r['during']['open']['answers']} (max {r['during']['open']['max_ms']:.0f} ms), with it "
                  f"{r['during']['operator']['answers']} (max {r['during']['operator']['max_ms']:.0f} ms); after it, "
                  f"the first answer in {r['after_flood_first_answer_ms'] or float('nan'):.0f} ms", flush=True)
            continue
        if name in ("held", "held+flood"):
            results[name] = r = held_presses(args.trials, args.check_ms / 1e3, flood=name == "held+flood")
            a = r["answer_ms"]
            print(f"{name}: {r['presses']} presses ({r['mid_chunk']} mid-chunk, safety check {args.check_ms:g} ms): "
                  f"{r['actions_after_held_answer']} actions started after a held answer, "
                  f"{r['stops_during_apply']} stops sent during an apply; answered p50 {a['p50']:.1f} ms, "
                  f"p99 {a['p99']:.1f} ms, max {a['max']:.1f} ms", flush=True)
            continue
        if name == "aborts":
            results["aborts"] = r = abort_runs(args.abort_runs, args.flood_seconds, args.nice, args.rt_priority)
            print(f"aborts: {r['aborts']}/{r['runs']} bridges died under a {args.flood_seconds:g} s flood with a "
                  f"controller; the controller's link held or lost in {r['controller_link_lost_or_held']} of the "
                  "surviving runs", flush=True)
            for line in r["abort_lines"]:
                print(f"  {line}")
            continue
        results[name] = r = scenario(name, args.trials, args.window, args.realtime, args.nice, args.rt_priority,
                                     args.process_fifo)
        e = r["estop"]
        answer, latched = _summary(e["answer_ms"]), _summary(e["latched_ms"])
        print(f"{name}: e-stop answered p50 {answer['p50_ms'] or float('nan'):.1f} ms, p99 "
              f"{answer['p99_ms'] or float('nan'):.1f} ms, max "
              f"{answer['max_ms'] or float('nan'):.1f} ms ({answer['over_100ms']}/{e['trials']} over 100 ms, "
              f"{e['unacknowledged']} unacknowledged, {e['failures']} failed)"
              + (f"; latched p50 {latched['p50_ms']:.1f} ms, max {latched['max_ms']:.1f} ms" if e["latched_ms"]
                 else "; latch time not reported") + f"; bridge {'alive' if r['bridge_alive'] else 'DIED'}",
              flush=True)
        ratio = r["rate_ratio"]
        print(f"  controller: {r['chunks_per_s_alone']:.1f} chunks/s alone, {r['chunks_per_s_loaded']:.1f} under "
              f"the load (ratio {ratio if ratio is None else round(ratio, 2)}); link events {r['link_events']}; "
              f"errors {r['controller_errors']}; load process {r['load']}", flush=True)
        if r["abort"]:
            print(f"  {r['abort']}")
    bar.close()
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=2)
    return 0


if __name__ == "__main__":
    ROLES[sys.argv[1]](sys.argv[2])
