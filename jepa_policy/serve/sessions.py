"""One robot's session on the policy server: its episode, frame history and the predictions awaiting their target."""
from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Session:
    """One connection's episode: its frame history, step counter and the predictions awaiting their target.

    The history holds the ``obs_steps`` frames a decision reads, oldest first. As in-process ``Policy.act``, a
    history that lacks frames (an episode's first step, or a gap in the steps) repeats its oldest frame; ``real``
    counts the frames that are not such copies, so a reply says ``history_padded`` exactly when a decision read one.
    """

    id: str
    obs_steps: int
    peer: str = ""
    episode: str = ""
    episodes: int = 0
    requests: int = 0
    history: deque = field(default_factory=deque)
    real: int = 0                                    # frames of the history that are not padding copies
    step: int = -1                                   # episode step of the newest frame seen
    pending: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)   # target step -> (t, z_hat)
    previous_chunk: tuple[int, np.ndarray] | None = None   # (step, normalised chunk) of the last decision: STAC
    prev_total_ms: float | None = None
    refused_in_row: int = 0                          # this connection's refused requests since its last accepted one

    def new_episode(self, episode: str | None) -> None:
        self.episodes += 1
        self.episode = episode or f"{self.id}-{self.episodes}"
        self.history = deque(maxlen=self.obs_steps)
        self.real = 0
        self.step = -1
        self.pending = {}
        self.previous_chunk = None

    def feed(self, frames: list[dict], newest_step: int | None) -> tuple[list[tuple[int, dict]], bool]:
        """Add frames (newest last) to the history; returns their (step, frame) and whether the history now holds
        padding (fewer than ``obs_steps`` consecutive real frames: an episode's start, or a gap in the steps)."""
        newest = self.step + len(frames) if newest_step is None else newest_step
        steps = list(range(newest - len(frames) + 1, newest + 1))
        if steps[0] != self.step + 1 or len(frames) >= self.obs_steps:
            self.history.clear()   # a gap (or a full history sent): the history restarts from these frames
            self.real = 0
        for frame in frames:
            if not self.history:
                self.history.extend([frame] * (self.obs_steps - 1))
            self.history.append(frame)
            self.real = min(self.real + 1, self.obs_steps)
        self.step = newest
        return list(zip(steps, frames)), self.real < self.obs_steps

    def drop_unmatched(self, most: int) -> int:
        """Forget predictions whose target step has passed unseen (the robot skipped that frame), and the oldest
        beyond ``most``: what the session keeps for the monitor stays bounded. Returns how many were dropped."""
        stale = [s for s in self.pending if s <= self.step]
        for s in stale:
            del self.pending[s]
        extra = sorted(self.pending)[:max(0, len(self.pending) - most)]
        for s in extra:
            del self.pending[s]
        return len(stale) + len(extra)


class PeerPenalties:
    """Refused requests per peer address (the host, not the connection: reconnecting does not reset them), each
    halving every ``half_life`` seconds; the ``most`` most recently refused addresses are remembered."""

    def __init__(self, half_life: float, most: int = 4096):
        self.half_life, self.most = half_life, most
        self._peers: OrderedDict[str, tuple[float, float]] = OrderedDict()   # host -> (penalty, when)

    def current(self, host: str, now: float) -> float:
        penalty, at = self._peers.get(host, (0.0, now))
        return penalty * 0.5 ** ((now - at) / self.half_life)

    def refused(self, host: str, now: float) -> float:
        """Count one refused request of ``host``; returns its penalty."""
        penalty = self.current(host, now) + 1.0
        self._peers[host] = (penalty, now)
        self._peers.move_to_end(host)
        while len(self._peers) > self.most:
            self._peers.popitem(last=False)
        return penalty


class RefusalBudget:
    """Refused requests of all peers together, ``rate`` cost units a second in bursts of ``burst`` (a generic cell
    rate algorithm: ``_tat`` is the time the budget is booked up to), so that rotating source addresses buys no more
    refusals than one address; refusals may book it at most ``backlog_s`` ahead."""

    def __init__(self, rate: float, burst: float, backlog_s: float):
        self.rate, self.burst, self.backlog_s = float(rate), float(burst), float(backlog_s)
        self._tat = 0.0

    def admit(self, now: float) -> float:
        """How long a new connection waits before it is let in: 0 while the budget lasts; once refusals spent it,
        each new connection books one unit too, so that those waiting are let in one by one at the budget's rate
        (never more than ``backlog_s`` later: a robot's connection is delayed, never turned away)."""
        spent = self.burst / self.rate
        if self._tat - now <= spent:
            return 0.0
        self._tat = min(self._tat + 1.0 / self.rate, now + spent + self.backlog_s)
        return min(self.backlog_s, self._tat - now - spent)

    def charge(self, now: float, cost: float) -> float | None:
        """Book one refused request of ``cost`` units; the pause before that connection's next frame is read, or
        None when the budget is booked more than ``backlog_s`` ahead (the connection is then closed, unbooked)."""
        tat = max(self._tat, now) + cost / self.rate
        turn = tat - now - self.burst / self.rate
        if turn > self.backlog_s:
            return None
        self._tat = tat
        return max(0.0, turn)
