"""The policy server's access and event log: one JSON object per line, rate-limited per kind of event.

Every line has ``ts`` (UTC, ISO 8601 with milliseconds), ``event`` and, where there is one, ``peer`` (address:port)
and ``session``. Events: ``connect``, ``disconnect`` (requests served, seconds, close code), ``unauthorized`` (an
HTTP 401: missing, wrong or repeated ``Authorization`` header; the key itself is never logged), ``refused`` (HTTP
503: the connection cap), ``rejected`` (a request answered with an error text), ``busy`` (a request refused by
the queue bound), ``error`` (a request the server failed on: a bug or a MemoryError, its traceback in the
``traceback`` field of the same line), ``tls_refused`` (a TLS handshake the server refused: no or an unknown
client certificate, plain HTTP on the TLS port, or a handshake stalled past its timeout), ``evicted`` (an untrusted
connection closed at the connection cap to let a new one in), ``accept_failed`` (the event loop could not accept a
connection: out of descriptors) and ``stop`` (monitor records that could not be delivered before the server
stopped).

A peer that floods the server with bad requests can neither flood the log nor hide another peer's lines: each
kind of event from each peer address has a token bucket (``burst`` lines, refilled at ``rate`` per second), and
all lines together a bucket of their own (``total_burst``, ``total_rate``); the next line of a (kind, address)
that passes says how many of its own were ``suppressed`` meanwhile, and ``suppressed_total`` how many lines of
any kind and peer the global cap left out since the last line written.
"""
from __future__ import annotations

import collections
import json
import logging
import threading
import time
from datetime import datetime, timezone

LOGGER = "jepa_policy.serve.events"


class EventLog:
    """Structured, rate-limited event lines on the ``jepa_policy.serve.events`` logger (INFO)."""

    def __init__(self, rate: float = 10.0, burst: int = 50, total_rate: float = 50.0, total_burst: int = 200,
                 logger: logging.Logger | None = None, clock=time.monotonic, remembered: int = 4096):
        self.rate, self.burst, self.clock = rate, burst, clock
        self.total_rate, self.total_burst, self.remembered = total_rate, total_burst, remembered
        self.logger = logger or logging.getLogger(LOGGER)
        # (event, peer address) -> (tokens, last refill, suppressed), most recent last
        self._buckets: collections.OrderedDict[tuple, tuple[float, float, int]] = collections.OrderedDict()
        self._total = (float(total_burst), clock(), 0)
        self._lock = threading.Lock()

    @staticmethod
    def _take(bucket: tuple[float, float, int], now: float, rate: float, burst: int) -> tuple[bool, tuple]:
        tokens, last, suppressed = bucket
        tokens = min(float(burst), tokens + (now - last) * rate)
        if tokens < 1.0:
            return False, (tokens, now, suppressed + 1)
        return True, (tokens - 1.0, now, suppressed)

    def emit(self, event: str, **fields) -> bool:
        """Log one event unless its (kind, peer address) or all lines together are over their rate; returns whether
        the line was written."""
        now = self.clock()
        peer = fields.get("peer")
        key = (event, peer.rsplit(":", 1)[0] if isinstance(peer, str) else None)
        with self._lock:
            bucket = self._buckets.pop(key, None) or (float(self.burst), now, 0)
            passed, bucket = self._take(bucket, now, self.rate, self.burst)
            self._buckets[key] = bucket
            while len(self._buckets) > self.remembered:
                self._buckets.popitem(last=False)
            if not passed:
                return False
            passed, self._total = self._take(self._total, now, self.total_rate, self.total_burst)
            if not passed:
                return False
            suppressed, left_out = bucket[2], self._total[2]
            self._buckets[key] = (bucket[0], bucket[1], 0)
            self._total = (self._total[0], self._total[1], 0)
        record = {"ts": datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z"),
                  "event": event, **{k: v for k, v in fields.items() if v is not None}}
        if suppressed:
            record["suppressed"] = suppressed
        if left_out:
            record["suppressed_total"] = left_out
        self.logger.info(json.dumps(record, default=str))
        return True


def log_to_stderr() -> None:
    """Write the event log to stderr, one JSON line each (``jepa-policy serve``: journald or a file redirect)."""
    logger = logging.getLogger(LOGGER)
    if not logger.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False
