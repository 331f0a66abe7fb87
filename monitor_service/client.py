"""Client for the robot loop: one non-blocking call per decision, delivered in order by a background drainer.

Records wait in a bounded in-memory buffer; a background thread (sync client) or task (async client) sends them
in order as msgpack batches, each with an Idempotency-Key kept across retries, so a batch that reached the server
before the link dropped is never counted twice. During an outage the buffer keeps records and retries with
back-off; when it is full new records are dropped (and counted) rather than blocking the control loop.
"""
from __future__ import annotations

import asyncio
import collections
import logging
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np

from monitor_service.encoding import MSGPACK_CONTENT_TYPE, pack

log = logging.getLogger(__name__)
_RETRYABLE = {408, 425, 429, 500, 502, 503, 504}


def _latent(x: Any, name: str) -> np.ndarray:
    arr = np.array(x, dtype="<f4", copy=True)  # a copy: the caller may reuse its buffer next step
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-D vector, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; the monitor accepts finite latents only")
    return arr


def _scores(scores: dict[str, float]) -> dict[str, float]:
    out = {}
    for name, value in scores.items():
        value = float(value)
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"score {name!r} is {value}; the monitor accepts finite, non-negative scores only")
        out[str(name)] = value
    return out


@dataclass
class ClientStats:
    """Counters of what happened to the records handed to the client."""

    queued: int = 0
    sent: int = 0
    dropped: int = 0
    rejected: list[tuple[dict, int, str]] = field(default_factory=list)  # (record, status, server message)


class _Records:
    """Builds records and owns the bounded buffer; shared by the sync and async clients."""

    def __init__(self, robot: str | None, max_buffer: int, batch_size: int, api_key: str, max_backoff: float):
        if max_buffer < 1 or batch_size < 1:
            raise ValueError("max_buffer and batch_size must be positive")
        self.api_key = api_key
        self.max_backoff = max_backoff
        self.robot = robot
        self.max_buffer = max_buffer
        self.batch_size = batch_size
        self.buffer: collections.deque[dict] = collections.deque()
        self.stats = ClientStats()

    def _put(self, record: dict) -> bool:
        raise NotImplementedError

    def decision(
        self, task: str, episode: str, step: int, horizon: int | None, z_hat: Any, *, checkpoint: str | None = None,
        held_out: bool = False, group: str | None = None, z_now: Any = None,
        scores: dict[str, float] | None = None,
    ) -> bool:
        """Queue one decision's predicted latent z_hat for step + horizon; False if the buffer was full.

        ``z_now``: the current latent E_rgb(o_step), optional; the service then also scores the persistence
        baseline (the paper's control, Sec. 4.10) and the ``nmse_ratio`` signal (NMSE over it). ``scores``:
        named per-decision risk scores of signals registered for the task ({"stac": 0.12}; finite, non-negative);
        with scores, z_hat and horizon may be None (a policy without a future head)."""
        rec: dict[str, Any] = {"kind": "decision", "task": task, "episode": episode, "step": int(step),
                               "held_out": bool(held_out)}
        if z_hat is not None:
            rec["horizon"], rec["z_hat"] = int(horizon), _latent(z_hat, "z_hat")
        if scores:
            rec["scores"] = _scores(scores)
        elif z_hat is None:
            raise ValueError("a decision needs z_hat (with horizon) or scores")
        if z_now is not None:
            rec["z_now"] = _latent(z_now, "z_now")
        if self.robot:
            rec["robot"] = self.robot
        if checkpoint is not None:
            rec["checkpoint"] = checkpoint
        if group is not None:
            rec["group"] = group
        return self._put(rec)

    def target(self, episode: str, step: int, z: Any) -> bool:
        """Queue the realized latent E_rgb(o_step); False if the buffer was full."""
        return self._put({"kind": "target", "episode": episode, "step": int(step), "z": _latent(z, "z")})

    def outcome(self, episode: str, success: bool, *, held_out: bool | None = None, group: str | None = None,
                length: int | None = None) -> bool:
        """Queue the episode's outcome (``length``: its env steps, for detection lead times); False if the
        buffer was full."""
        rec: dict[str, Any] = {"kind": "outcome", "episode": episode, "success": bool(success)}
        if length is not None:
            rec["length"] = int(length)
        if held_out is not None:
            rec["held_out"] = held_out
        if group is not None:
            rec["group"] = group
        return self._put(rec)

    @property
    def pending(self) -> int:
        return len(self.buffer)


def _detail(response: httpx.Response) -> str:
    try:
        return str(response.json().get("detail", response.text))
    except ValueError:
        return response.text


def _headers(api_key: str, key: str) -> dict[str, str]:
    return {"X-API-Key": api_key, "Idempotency-Key": key, "Content-Type": MSGPACK_CONTENT_TYPE}


class MonitorClient(_Records):
    """Synchronous client with a background sender thread. Use as a context manager or call close()."""

    def __init__(
        self, base_url: str, api_key: str, *, robot: str | None = None, max_buffer: int = 100_000,
        batch_size: int = 256, timeout: float = 5.0, max_backoff: float = 1.0,
        on_result: Any = None,
    ):
        """``on_result(records, result)``: called from the sender thread with each accepted batch and the
        service's answer (``alert_state``: each touched episode's open alert), e.g. to act on alerts."""
        super().__init__(robot, max_buffer, batch_size, api_key, max_backoff)
        self.on_result = on_result
        self._http = httpx.Client(base_url=base_url, timeout=timeout)
        self._cond = threading.Condition()
        self._closing = False
        self._abandon = threading.Event()  # set by close(): stop retrying and leave the rest unsent
        self._thread = threading.Thread(target=self._run, name="monitor-client", daemon=True)
        self._thread.start()

    def _put(self, record: dict) -> bool:
        with self._cond:
            if len(self.buffer) >= self.max_buffer:
                self.stats.dropped += 1
                return False
            self.buffer.append(record)
            self.stats.queued += 1
            self._cond.notify()
        return True

    def _post(self, records: list[dict], key: str) -> httpx.Response:
        return self._http.post("/v1/batch", content=pack({"records": records}), headers=_headers(self.api_key, key))

    def _send_until_done(self, records: list[dict], key: str) -> httpx.Response | None:
        backoff = 0.02
        while True:
            try:
                response = self._post(records, key)
                if response.status_code not in _RETRYABLE:
                    return response
            except httpx.TransportError as exc:
                log.debug("monitor link down (%s); retrying", exc)
            # A separate event, not the buffer's condition: new records must not cut the back-off short.
            if self._abandon.wait(backoff):
                return None
            backoff = min(backoff * 2, self.max_backoff)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self.buffer and not self._closing:
                    self._cond.wait()
                if not self.buffer and self._closing:
                    return
                batch = [self.buffer[i] for i in range(min(self.batch_size, len(self.buffer)))]
            response = self._send_until_done(batch, uuid.uuid4().hex)
            if response is None:
                return
            if response.status_code < 300 and self.on_result is not None:
                try:
                    self.on_result(batch, response.json())
                except Exception:   # a callback's bug must not stop delivery
                    log.exception("monitor client on_result callback failed")
            if response.status_code >= 300 and len(batch) == 1:
                self.stats.rejected.append((batch[0], response.status_code, _detail(response)))
                log.warning("monitor refused a %s record: %s", batch[0]["kind"], response.text)
            elif response.status_code >= 300:
                # One bad record must not sink its neighbours: resend one by one and keep the refusals.
                for rec in batch:
                    single = self._send_until_done([rec], uuid.uuid4().hex)
                    if single is None:
                        return
                    if single.status_code >= 300:
                        self.stats.rejected.append((rec, single.status_code, _detail(single)))
                        log.warning("monitor refused a %s record: %s", rec["kind"], single.text)
            with self._cond:
                for _ in batch:
                    self.buffer.popleft()
                self.stats.sent += len(batch)
                self._cond.notify_all()

    def flush(self, timeout: float = 30.0) -> bool:
        """Wait until every queued record was answered by the server; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self.buffer:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.05))
        return True

    def close(self, timeout: float = 30.0) -> bool:
        """Flush (up to ``timeout``), stop the sender and release the connection; False if records were left."""
        done = self.flush(timeout)
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._abandon.set()
        self._thread.join(timeout=max(self.max_backoff * 2, 5.0))
        self._http.close()
        return done

    def __enter__(self) -> MonitorClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class AsyncMonitorClient(_Records):
    """Asyncio client: the record calls are plain (non-awaiting) methods; a task drains the buffer.

    Create it inside a running event loop (``async with AsyncMonitorClient(...) as client``).
    """

    def __init__(
        self, base_url: str, api_key: str, *, robot: str | None = None, max_buffer: int = 100_000,
        batch_size: int = 256, timeout: float = 5.0, max_backoff: float = 1.0,
    ):
        super().__init__(robot, max_buffer, batch_size, api_key, max_backoff)
        self._http = httpx.AsyncClient(base_url=base_url, timeout=timeout)
        self._wake = asyncio.Event()
        self._closing = False
        self._task = asyncio.get_running_loop().create_task(self._run())

    def _put(self, record: dict) -> bool:
        if len(self.buffer) >= self.max_buffer:
            self.stats.dropped += 1
            return False
        self.buffer.append(record)
        self.stats.queued += 1
        self._wake.set()
        return True

    async def _send_until_done(self, records: list[dict], key: str) -> httpx.Response | None:
        backoff = 0.02
        body = pack({"records": records})
        while True:
            try:
                response = await self._http.post("/v1/batch", content=body, headers=_headers(self.api_key, key))
                if response.status_code not in _RETRYABLE:
                    return response
            except httpx.TransportError as exc:
                log.debug("monitor link down (%s); retrying", exc)
            if self._closing:
                return None
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2, self.max_backoff)

    async def _run(self) -> None:
        while True:
            if not self.buffer:
                if self._closing:
                    return
                self._wake.clear()
                await self._wake.wait()
                continue
            batch = [self.buffer[i] for i in range(min(self.batch_size, len(self.buffer)))]
            response = await self._send_until_done(batch, uuid.uuid4().hex)
            if response is None:
                return
            if response.status_code >= 300 and len(batch) == 1:
                self.stats.rejected.append((batch[0], response.status_code, _detail(response)))
            elif response.status_code >= 300:
                for rec in batch:
                    single = await self._send_until_done([rec], uuid.uuid4().hex)
                    if single is None:
                        return
                    if single.status_code >= 300:
                        self.stats.rejected.append((rec, single.status_code, _detail(single)))
            for _ in batch:
                self.buffer.popleft()
            self.stats.sent += len(batch)

    async def flush(self, timeout: float = 30.0) -> bool:
        """Wait until every queued record was answered by the server; False on timeout."""
        deadline = time.monotonic() + timeout
        while self.buffer:
            if time.monotonic() > deadline or self._task.done():
                return False
            await asyncio.sleep(0.01)
        return True

    async def close(self, timeout: float = 30.0) -> bool:
        """Flush (up to ``timeout``), stop the drain task and close the connection; False if records were left."""
        done = await self.flush(timeout)
        self._closing = True
        self._wake.set()
        try:
            await asyncio.wait_for(self._task, timeout=max(self.max_backoff * 2, 5.0))
        except asyncio.TimeoutError:
            self._task.cancel()
        await self._http.aclose()
        return done

    async def __aenter__(self) -> AsyncMonitorClient:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()
