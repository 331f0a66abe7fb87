"""A lean check of ingest bodies: plain Python over the decoded records and one NumPy pass over all of a
request's latents, instead of a pydantic model per record.

It accepts only what the pydantic models (``schemas.py``) accept, and only in their plain forms (integers as
ints, latents as float32 arrays or lists of numbers); anything else, valid or not, returns None and the caller
validates with pydantic, so every error a client sees is pydantic's, word for word. ``tests/monitor_service/
test_validation.py`` checks the equivalence on valid and invalid records.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from monitor_service.schemas import F32_MAX, MAX_HORIZON, MAX_SIGNALS, MAX_STEP, RESERVED_SIGNALS

NAME = re.compile(r"^[A-Za-z0-9_.:\-]+$")
MAX_RECORDS = 10_000
LITTLE_F32 = np.dtype("<f4")   # a singleton: the msgpack decoder's arrays have exactly this dtype
DECISION_KEYS = frozenset({"kind", "task", "episode", "step", "horizon", "z_hat", "scores", "z_now", "robot",
                           "checkpoint", "held_out", "group"})
TARGET_KEYS = frozenset({"kind", "episode", "step", "z"})
OUTCOME_KEYS = frozenset({"kind", "episode", "success", "held_out", "group", "length"})


@dataclass(slots=True)
class Decision:
    """A checked decision record, read like ``schemas.DecisionIn``."""

    task: str
    episode: str
    step: int
    horizon: int | None
    z_hat: np.ndarray | None
    scores: dict[str, float] | None
    z_now: np.ndarray | None
    robot: str | None
    checkpoint: str | None
    held_out: bool
    group: str | None
    kind: str = "decision"


@dataclass(slots=True)
class Target:
    episode: str
    step: int
    z: np.ndarray
    kind: str = "target"


@dataclass(slots=True)
class Outcome:
    episode: str
    success: bool
    held_out: bool | None
    group: str | None
    length: int | None
    kind: str = "outcome"


class _Unusual(Exception):
    """Not in the plain form this check handles: let pydantic decide (and word any error)."""


class _Names:
    """Names already matched against the pattern (a robot's few task and episode ids recur in every request)."""

    def __init__(self, limit: int = 100_000):
        self.seen: set[str] = set()
        self.limit = limit

    def check(self, value: Any, optional: bool = False) -> str | None:
        if value is None and optional:
            return None
        if type(value) is not str:
            raise _Unusual
        if value not in self.seen:
            if not 1 <= len(value) <= 128 or NAME.match(value) is None:
                raise _Unusual
            if len(self.seen) >= self.limit:
                self.seen.clear()
            self.seen.add(value)
        return value


NAMES = _Names()


def _int(value: Any, low: int, high: int) -> int:
    if type(value) is not int or not low <= value <= high:
        raise _Unusual
    return value


def _latent(value: Any, latents: list[np.ndarray]) -> np.ndarray:
    """A float32 1-D array (msgpack) or a list of numbers (JSON); its finiteness is checked with all the others."""
    if type(value) is np.ndarray:
        if value.dtype is not LITTLE_F32 or value.ndim != 1 or not value.size:   # anything else: pydantic's words
            raise _Unusual
        array = value
    elif type(value) is list:
        if not value or not set(map(type, value)) <= {float, int}:
            raise _Unusual
        try:
            wide = np.asarray(value, dtype=np.float64)
        except OverflowError:   # an integer beyond float64
            raise _Unusual from None
        if not np.isfinite(wide).all() or np.abs(wide).max() > F32_MAX:
            raise _Unusual
        array = wide.astype("<f4")
    else:
        raise _Unusual
    latents.append(array)
    return array


def _scores(value: Any) -> dict[str, float] | None:
    if value is None:
        return None
    if type(value) is not dict or len(value) > MAX_SIGNALS:
        raise _Unusual
    out = {}
    for name, v in value.items():
        NAMES.check(name)
        if name in RESERVED_SIGNALS or type(v) not in (float, int) or not 0 <= v < float("inf"):
            raise _Unusual   # NaN fails 0 <= v
        out[name] = float(v)
    return out


def _record(rec: Any, latents: list[np.ndarray], route_kind: str | None):
    if type(rec) is not dict:
        raise _Unusual
    kind = rec.get("kind", route_kind)
    if kind is None or (route_kind is not None and kind != route_kind):   # pydantic infers or refuses it
        raise _Unusual
    if kind == "decision":
        if not rec.keys() <= DECISION_KEYS:
            raise _Unusual
        z_hat, horizon = rec.get("z_hat"), rec.get("horizon")
        if (z_hat is None) != (horizon is None):
            raise _Unusual
        scores = _scores(rec.get("scores"))
        if z_hat is None and not scores:
            raise _Unusual
        z_now = rec.get("z_now")
        checkpoint = rec.get("checkpoint")
        if checkpoint is not None and (type(checkpoint) is not str or len(checkpoint) > 256):
            raise _Unusual
        held_out = rec.get("held_out", False)
        if type(held_out) is not bool or (z_now is not None and z_hat is None):
            raise _Unusual
        return Decision(NAMES.check(rec.get("task")), NAMES.check(rec.get("episode")),
                        _int(rec.get("step"), 0, MAX_STEP),
                        None if horizon is None else _int(horizon, 1, MAX_HORIZON),
                        None if z_hat is None else _latent(z_hat, latents), scores,
                        None if z_now is None else _latent(z_now, latents), NAMES.check(rec.get("robot"), True),
                        checkpoint, held_out, NAMES.check(rec.get("group"), True))
    if kind == "target":
        if not rec.keys() <= TARGET_KEYS or "z" not in rec:
            raise _Unusual
        return Target(NAMES.check(rec.get("episode")), _int(rec.get("step"), 0, MAX_STEP + MAX_HORIZON),
                      _latent(rec["z"], latents))
    if kind == "outcome":
        if not rec.keys() <= OUTCOME_KEYS or type(rec.get("success")) is not bool:
            raise _Unusual
        held_out, length = rec.get("held_out"), rec.get("length")
        if held_out is not None and type(held_out) is not bool:
            raise _Unusual
        return Outcome(NAMES.check(rec.get("episode")), rec["success"], held_out, NAMES.check(rec.get("group"), True),
                       None if length is None else _int(length, 1, MAX_STEP + MAX_HORIZON))
    raise _Unusual


def plain_records(payload: Any, route_kind: str | None) -> list | None:
    """The records of a decoded body when every one is in plain valid form, else None (then pydantic validates
    the body and words the error). ``route_kind``: the kind of a single-record route, None for a batch
    ``{"records": [...]}``."""
    try:
        if route_kind is None:
            if type(payload) is not dict or payload.keys() != {"records"}:
                raise _Unusual
            raw = payload["records"]
            if type(raw) is not list or not 1 <= len(raw) <= MAX_RECORDS:
                raise _Unusual
        else:
            raw = [payload]
        latents: list[np.ndarray] = []
        records = [_record(r, latents, route_kind) for r in raw]
        if latents and not np.isfinite(np.concatenate(latents)).all():   # one pass over all of them
            raise _Unusual
        return records
    except _Unusual:
        return None
