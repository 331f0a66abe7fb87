"""The policy server's access and event log: one JSON object per line, rate-limited per kind of event.

Every line has ``ts`` (UTC, ISO 8601 with milliseconds), ``event`` and, where there is one, ``peer`` (address:port)
and ``session``. Events: ``connect``, ``disconnect`` (requests served, seconds, close code), ``unauthorized`` (an
HTTP 401: missing, wrong or repeated ``Authorization`` header; the key itself is never logged), ``refused`` (HTTP
503: the connection cap), ``rejected`` (a request answered with an error text), ``busy`` (a request refused by
the queue bound), ``error`` (a request the server failed on: a bug or a MemoryError, its traceback in the
``traceback`` field of the same line), ``tls_refused`` (a TLS handshake the server refused: no or an unknown
client certificate, plain HTTP on the TLS port) and ``stop`` (monitor records that could not be delivered before
the server stopped). A peer that floods the
server with bad requests cannot flood the log: each kind of event has a token bucket (``burst`` lines, refilled
at ``rate`` per second); the next line of that kind that passes says how many were ``suppressed`` meanwhile.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from datetime import datetime, timezone

LOGGER = "jepa_policy.serve.events"


class EventLog:
    """Structured, rate-limited event lines on the ``jepa_policy.serve.events`` logger (INFO)."""

    def __init__(self, rate: float = 10.0, burst: int = 50, logger: logging.Logger | None = None, clock=time.monotonic):
        self.rate, self.burst, self.clock = rate, burst, clock
        self.logger = logger or logging.getLogger(LOGGER)
        self._buckets: dict[str, tuple[float, float, int]] = {}   # event -> (tokens, last refill, suppressed)
        self._lock = threading.Lock()

    def emit(self, event: str, **fields) -> bool:
        """Log one event unless its kind is over its rate; returns whether the line was written."""
        now = self.clock()
        with self._lock:
            tokens, last, suppressed = self._buckets.get(event, (float(self.burst), now, 0))
            tokens = min(float(self.burst), tokens + (now - last) * self.rate)
            if tokens < 1.0:
                self._buckets[event] = (tokens, now, suppressed + 1)
                return False
            self._buckets[event] = (tokens - 1.0, now, 0)
        record = {"ts": datetime.now(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z"),
                  "event": event, **{k: v for k, v in fields.items() if v is not None}}
        if suppressed:
            record["suppressed"] = suppressed
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
