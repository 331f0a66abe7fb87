"""Alert logic: a debounced, hysteretic threshold crossing per episode, and webhook delivery with retries."""
from __future__ import annotations

import asyncio
import datetime as dt
import logging
from dataclasses import dataclass

import httpx
from sqlalchemy import select, update
from sqlalchemy.orm import sessionmaker

from monitor_service.db import Alert, WebhookDelivery, utcnow
from monitor_service.metrics import WEBHOOK_FAILURES

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AlertState:
    """Per-episode counters of consecutive evaluations above / below the hysteresis band, and whether it is raised."""

    over: int = 0
    under: int = 0
    raised: bool = False


def step_alert(state: AlertState, score: float, threshold: float, debounce: int,
               clear_level: float) -> tuple[AlertState, str | None]:
    """Advance the alert state by one evaluation of the running statistic.

    Raise after ``debounce`` consecutive scores above ``threshold``; once raised, clear only after ``debounce``
    consecutive scores below ``clear_level`` (hysteresis, ``rules.clear_level``). Scores inside the band reset
    the opposite counter, so a score wobbling around the threshold cannot flap the alert. Returns the new state
    and "raise", "clear" or None. Whether an episode ever raises depends only on threshold and debounce, which
    is what ``rules.alert_statistic`` calibrates.
    """
    if not state.raised:
        over = state.over + 1 if score > threshold else 0
        if over >= debounce:
            return AlertState(0, 0, True), "raise"
        return AlertState(over, 0, False), None
    under = state.under + 1 if score < clear_level else 0
    if under >= debounce:
        return AlertState(0, 0, False), "clear"
    return AlertState(0, under, True), None


def alert_payload(alert: Alert) -> dict:
    """The JSON body sent to webhooks and over the SSE stream."""
    return {
        "id": alert.id,
        "episode_id": alert.episode_id,
        "task": alert.task,
        "robot": alert.robot,
        "step": alert.step,
        "score": alert.score,
        "threshold": alert.threshold,
        "state": alert.state,
        "acknowledged_by": alert.acknowledged_by,
        "beyond_calibration": alert.beyond_calibration,
        "no_promise": bool(alert.no_promise),
        "note": alert.note,
        "signals": alert.signals,
        "raised_at": alert.raised_at.isoformat() + "Z",
    }


def _claim_due(make_session: sessionmaker, lease_s: float) -> list[tuple[int, str, dict]]:
    """Claim due deliveries with a conditional UPDATE each, so several workers never post the same one at once."""
    now = utcnow()
    claimed = []
    with make_session() as session:
        due = session.scalars(
            select(WebhookDelivery)
            .where(WebhookDelivery.status == "pending", WebhookDelivery.next_attempt_at <= now).limit(50)
        ).all()
        for delivery in due:
            won = session.execute(
                update(WebhookDelivery)
                .where(
                    WebhookDelivery.id == delivery.id,
                    WebhookDelivery.status == "pending",
                    (WebhookDelivery.claimed_until.is_(None)) | (WebhookDelivery.claimed_until < now),
                )
                .values(claimed_until=now + dt.timedelta(seconds=lease_s))
            ).rowcount
            if won:
                claimed.append((delivery.id, delivery.url, alert_payload(session.get(Alert, delivery.alert_id))))
        session.commit()
    return claimed


def _record_attempt(make_session: sessionmaker, delivery_id: int, error: str, max_attempts: int,
                    backoff_s: float) -> None:
    with make_session() as session:
        delivery = session.get(WebhookDelivery, delivery_id)
        delivery.attempts += 1
        delivery.claimed_until = None
        if not error:
            delivery.status, delivery.last_error = "delivered", ""
        else:
            WEBHOOK_FAILURES.inc()
            delivery.last_error = error[:1000]
            if delivery.attempts >= max_attempts:
                delivery.status = "failed"
                log.warning("webhook %s gave up after %d attempts: %s", delivery.url, delivery.attempts, error)
            else:
                delivery.next_attempt_at = utcnow() + dt.timedelta(seconds=backoff_s * 2 ** (delivery.attempts - 1))
        session.commit()


async def deliver_pending(
    make_session: sessionmaker, client: httpx.AsyncClient, max_attempts: int, backoff_s: float, lease_s: float = 30.0
) -> int:
    """Post every due webhook delivery once; returns how many were attempted.

    Failures back off exponentially (backoff_s * 2^(attempt-1)) until ``max_attempts``, then are marked failed.
    Database work runs in a thread so the event loop never waits on a lock.
    """
    claimed = await asyncio.to_thread(_claim_due, make_session, lease_s)
    for delivery_id, url, body in claimed:
        error = ""
        try:
            response = await client.post(url, json=body, headers={"X-Jepa-Monitor-Delivery": str(delivery_id)})
            if response.status_code >= 300:
                error = f"HTTP {response.status_code}"
        except httpx.HTTPError as exc:
            error = f"{type(exc).__name__}: {exc}"
        await asyncio.to_thread(_record_attempt, make_session, delivery_id, error, max_attempts, backoff_s)
    return len(claimed)


async def webhook_loop(make_session: sessionmaker, settings, stop: asyncio.Event, poll_s: float = 0.2) -> None:
    """Background task of each worker: deliver webhooks until ``stop`` is set."""
    async with httpx.AsyncClient(timeout=settings.webhook_timeout_s) as client:
        while not stop.is_set():
            try:
                await deliver_pending(make_session, client, settings.webhook_max_attempts, settings.webhook_backoff_s)
            except Exception:  # keep delivering after a transient database error; it is logged, not hidden
                log.exception("webhook delivery pass failed")
            try:
                await asyncio.wait_for(stop.wait(), poll_s)
            except asyncio.TimeoutError:
                pass
