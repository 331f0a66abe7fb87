"""The bridge's resources under a flood: its open connections against its descriptor limit, and its memory.

Two floods no budget of the sockets can stop:

* **Descriptors.** Every connection to either socket holds a descriptor of the bridge's process, whether it sends
  anything or not. At the process's limit (``RLIMIT_NOFILE``; systemd's default soft limit is 1,024) libzmq can
  no longer accept a connection: it retries the accept in a loop and the operator's next e-stop never arrives.
* **Memory.** libzmq bounds each frame of a message (``MAXMSGSIZE``) but neither how many frames a message has nor
  the bytes a connection queues (``RCVHWM`` counts messages), and it delivers a message whole: one message of
  25,000 frames of 4,000 bytes is buffered before the bridge can read a byte of it (about three times its size).

The guard's thread counts each socket's open connections from ZeroMQ socket monitors (accepted, disconnected;
resynchronised every second with ``/proc/self/fd``) and reads the process's resident memory at every turn (at most
``POLL_MS`` apart). When the descriptors in use pass ``FD_FRACTION`` of the limit, or the memory passes
``max_rss_mb``, it latches the e-stop with a reason that names the cause: a bridge that may lose its e-stop channel
(or its process) stops the robot, fail-safe. Each trip is counted (``connection_guard``, ``memory_guard``) and
logged, and the guard arms again once the use is back under ``REARM`` of its bound; memory, which a process seldom
gives back, also trips again each time it grows by ``MEMORY_STEP`` of its bound past the last trip's reading (so
a second flood after the operator's clear latches again, before the kernel's OOM kill). A descriptor trip and a
re-arm are each decided on a fresh count of ``/proc/self/fd`` (the estimate where it cannot be read): the monitors'
events run behind the descriptors, so between resynchronisations the estimate can count a connection twice. It
never releases the latch: after the flood, ``status`` and ``clear-estop`` work again and the operator clears it.

The guard also hands the control socket's disconnects to the event loop (a socket has one monitor), which needs
them to see the controlling client's connection close (``RobotBridge._serve_monitor``).
"""
from __future__ import annotations

import collections
import itertools
import logging
import os
import resource
import struct
import threading
import time

import zmq

from jepa_robot.estop import EStop

log = logging.getLogger(__name__)

DEFAULT_MAX_RSS_MB = 2048.0   # the bridge's resident memory at which the guard latches the e-stop (--max-rss-mb)
FD_FRACTION = 0.75     # descriptors in use, of the limit, at which the e-stop latches
REARM = 0.6            # ... and below which (of either bound) the guard may trip again
MEMORY_STEP = 0.25     # memory only: above its bound, each growth by this share of the bound past the last trip's
                       # reading trips again (a process seldom returns freed memory: after a flood the resident
                       # memory may never fall back under REARM, and a second flood would find the guard disarmed)
POLL_MS = 50
RESYNC_S = 1.0         # the monitors' count checked against /proc/self/fd this often
_EVENTS = zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096
_ids = itertools.count()


def descriptor_limit() -> int:
    """The process's soft limit on open descriptors (what the guard measures against)."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    return soft if soft != resource.RLIM_INFINITY else 2**31


def open_descriptors() -> int | None:
    """Descriptors this process holds now (Linux), None where the platform does not say."""
    try:
        return len(os.listdir("/proc/self/fd")) - 1   # less the one listdir itself opened
    except OSError:
        return None


def resident_mb() -> float | None:
    """The process's resident memory in MiB now (Linux), None where the platform does not say."""
    try:
        with open("/proc/self/statm", "rb") as f:
            return int(f.read().split()[1]) * _PAGE / 2**20
    except (OSError, IndexError, ValueError):
        return None


class ResourceGuard:
    """Watches ``sockets`` (name -> bound socket, monitored from now on) and the process's memory in a thread of its
    own; presses ``estop`` when either runs short (module docstring)."""

    def __init__(self, ctx: zmq.Context, sockets: dict[str, zmq.Socket], estop: EStop,
                 max_rss_mb: float | None, forward: str = "control"):
        self.estop = estop
        self.max_rss_mb = max_rss_mb
        self.limit = descriptor_limit()
        self.connections = {name: 0 for name in sockets}
        self.counters: collections.Counter = collections.Counter()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._armed = {"descriptors": True, "memory": True}
        self._memory_mark: float | None = None   # the resident memory at the last memory trip (MEMORY_STEP)
        self._forward = forward
        prefix = f"inproc://robot-bridge-guard-{next(_ids)}"
        self._monitors: dict[zmq.Socket, str] = {}
        for name, sock in sockets.items():
            sock.monitor(f"{prefix}-{name}", _EVENTS)
            pair = ctx.socket(zmq.PAIR)
            pair.setsockopt(zmq.LINGER, 0)
            # unbounded: a full monitor pipe blocks the socket's I/O thread (libzmq sends events blocking); these
            # two events per connection are read every turn
            pair.setsockopt(zmq.RCVHWM, 0)
            pair.connect(f"{prefix}-{name}")
            self._monitors[pair] = name
        self.disconnect_address = f"{prefix}-disconnects"
        self._disconnects = ctx.socket(zmq.PUSH)
        self._disconnects.setsockopt(zmq.LINGER, 0)
        self._disconnects.bind(self.disconnect_address)
        self._baseline = max(0, (open_descriptors() or 0))
        self._synced = time.monotonic()
        self.rss_mb = resident_mb()

    # ------------------------------------------------------------ thread
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="robot-bridge-guard", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
            self._thread = None
        else:
            self._close()

    def _close(self) -> None:
        for sock in (*self._monitors, self._disconnects):
            sock.close(linger=0)

    def _run(self) -> None:
        poller = zmq.Poller()
        for pair in self._monitors:
            poller.register(pair, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                try:
                    for pair, _ in poller.poll(POLL_MS):
                        self._drain(pair)
                    self.check(time.monotonic())
                except Exception:   # a bug here must not end the guard; the e-stop does not depend on it
                    self._count("internal_errors")
                    log.exception("resource guard error; it goes on")
                    time.sleep(POLL_MS / 1000)
        finally:
            self._close()

    def _drain(self, pair: zmq.Socket) -> None:
        name = self._monitors[pair]
        while True:
            try:
                frames = pair.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            event = struct.unpack("=H", frames[0][:2])[0]
            if event == zmq.EVENT_ACCEPTED:
                self.connections[name] += 1
            elif event == zmq.EVENT_DISCONNECTED:
                self.connections[name] = max(0, self.connections[name] - 1)
                if name == self._forward:
                    try:
                        self._disconnects.send_multipart(frames, zmq.NOBLOCK)
                    except zmq.Again:   # the loop is behind; its probes notice a closed client anyway
                        self._count("disconnects_dropped")

    # ------------------------------------------------------------ the bounds
    def descriptors(self, now: float, fresh: bool = False) -> int:
        """Descriptors in use: the count at the last resynchronisation plus the connections opened since (``fresh``:
        resynchronise now)."""
        connections = sum(self.connections.values())
        if fresh or now - self._synced >= RESYNC_S:
            counted = open_descriptors()
            if counted is not None:
                self._baseline = max(0, counted - connections)
            self._synced = now
        return self._baseline + connections

    def check(self, now: float) -> None:
        """One look at both bounds; trips (presses the e-stop) where one is passed and the guard is armed."""
        used = self.descriptors(now)
        bound, rearm = FD_FRACTION * self.limit, REARM * self.limit
        armed = self._armed["descriptors"]
        if ((armed and used >= bound) or (not armed and used < rearm)) and self._synced != now:
            # a trip or a re-arm is decided on a fresh count (the estimate where none can be read, e.g. at the
            # limit itself): the monitors' events run behind the descriptors, so the estimate can count a
            # connection twice, its descriptor at a resynchronisation and its accept event after it (the
            # connections a closed flood left in the listen backlog, accepted once the guard re-armed, could so
            # trip it a second time); not twice in one look, when the estimate has just been resynchronised
            used = self.descriptors(now, fresh=True)
        if used >= bound:
            if self._armed["descriptors"]:
                self._armed["descriptors"] = False
                c = self.connections
                self._trip("connection_guard", f"the bridge holds {used} of its {self.limit} descriptors ("
                           + ", ".join(f"{n} connections on the {k} socket" for k, n in c.items())
                           + f"), past {FD_FRACTION:.0%} of its limit: a flood of connections could leave no "
                             "descriptor for the operator's e-stop, so the robot holds (fail-safe); find the process "
                             "that opens them (ss -tnp), stop it, then clear-estop")
        elif used < rearm:
            self._armed["descriptors"] = True
        self.rss_mb = resident_mb()
        if self.max_rss_mb is None or self.rss_mb is None:
            return
        if self.rss_mb >= self.max_rss_mb:
            mark = self._memory_mark
            if self._armed["memory"] or (mark is not None and self.rss_mb >= mark + MEMORY_STEP * self.max_rss_mb):
                self._armed["memory"] = False
                self._memory_mark = self.rss_mb
                self._trip("memory_guard", f"the bridge's memory ({self.rss_mb:.0f} MiB resident) passed its bound "
                                           f"({self.max_rss_mb:.0f} MiB, --max-rss-mb): a flood of oversized "
                                           "messages could end its process, so the robot holds (fail-safe); find the "
                                           "process that sends them (ss -tnp), stop it, then clear-estop")
        elif self.rss_mb < REARM * self.max_rss_mb:
            self._armed["memory"] = True
            self._memory_mark = None

    def _trip(self, counter: str, reason: str) -> None:
        self._count(counter)
        log.error("resource guard: %s", reason)
        self.estop.press(reason)

    def _count(self, name: str) -> None:
        with self._lock:
            self.counters[name] += 1

    def counts(self) -> dict:
        with self._lock:
            return dict(self.counters)

    def facts(self) -> dict:
        """What ``status`` shows of the guard: connections per socket, descriptors, memory and their bounds."""
        return {"connections": dict(self.connections), "descriptors": self._baseline + sum(self.connections.values()),
                "descriptor_limit": self.limit, "descriptor_trip": int(FD_FRACTION * self.limit),
                "rss_mb": None if self.rss_mb is None else round(self.rss_mb, 1), "max_rss_mb": self.max_rss_mb}
