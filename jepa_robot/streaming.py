"""Asynchronous execution's queue on the bridge's clock (``stream``; real-time chunking, docs/real_robot.md).

A chunk predicted from the observation of step ``o`` arrives at step ``s``: its first ``s - o`` actions are in the
past and dropped, and the rest replaces whatever was left of the queue. The bridge takes one action per control
period (``RobotBridge._stream_tick``); a period with an empty queue holds the robot and is counted as an
underflow. Pure bookkeeping: the bridge does the moving.
"""
from __future__ import annotations

import collections

import numpy as np


class StreamQueue:
    """The queued actions, the next tick, the underflows and the safety reports not yet sent to the client."""

    def __init__(self):
        self.active = False            # the episode streams: one action per tick
        self.waiting = False           # its budget is spent: the operator confirms the outcome
        self.actions: collections.deque = collections.deque()
        self.next_tick = 0.0
        self.underflow_steps = 0
        self.reports: list[dict] = []  # violations since the client's last ``observe``

    def reset(self) -> None:
        """A new episode (synchronous until its first ``stream``)."""
        self.__init__()

    def stop(self) -> None:
        self.active = self.waiting = False
        self.actions.clear()

    def replace(self, actions: np.ndarray, late: int, now: float) -> int:
        """A chunk ``late`` steps behind: what is left of it replaces the queue; starts the clock; accepted count."""
        self.actions = collections.deque(actions[late:])
        if not self.active:
            self.active, self.next_tick = True, now
        return len(self.actions)

    def tick(self, now: float, period: float) -> None:
        """Schedule the next tick; never bursts to catch up after a late one."""
        self.next_tick = max(self.next_tick + period, now)

    def take_reports(self) -> list[dict]:
        reports, self.reports = self.reports, []
        return reports
