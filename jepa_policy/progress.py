"""Rollouts on a progress bar: what ``jepa-policy eval`` and ``protocols --select`` show on stderr while they run;
and whether bars are wanted at all (``TQDM_DISABLE``, which ``jepa-demo --no-progress`` sets for its processes)."""
from __future__ import annotations

import os
import time
from contextlib import contextmanager


def bars_disabled() -> bool:
    """True when the environment turns tqdm's bars off (tqdm's own ``TQDM_DISABLE``, inherited by the processes a
    job spawns); a bar whose ``disable`` is passed explicitly would otherwise ignore it."""
    return os.environ.get("TQDM_DISABLE", "").strip().lower() in ("1", "true", "yes")


class EpisodeProgress:
    """An ``EnvPool`` whose resets move a tqdm bar of finished episodes; everything else is the pool's own.

    ``evaluate`` plays rounds of lockstep episodes and resets the pool at the start of each, so a reset means the
    episodes of the round before it have ended. A round rerun after a worker failed resets the same seeds again
    and is counted once. Call ``finish`` when ``evaluate`` returns: its last round ended too.
    """

    def __init__(self, pool, bar):
        self._pool, self._bar = pool, bar
        self._seeds: tuple = ()
        self._running = 0

    def reset(self, seeds, active=None):
        if tuple(seeds) != self._seeds:        # a new round, not a rerun of the last one
            self._bar.update(self._running)
        self._seeds = tuple(seeds)
        self._running = len(seeds) if active is None else int(sum(bool(a) for a in active))
        return self._pool.reset(seeds, active=active)

    def finish(self) -> None:
        self._bar.update(self._running)
        self._seeds, self._running = (), 0

    def __getattr__(self, name):
        return getattr(self._pool, name)


class Timer:
    """Wall time of each named step of a job (jepa-demo's PushT and pick jobs), printed as it goes."""

    def __init__(self):
        self.steps: dict[str, float] = {}
        self.start = time.perf_counter()

    @contextmanager
    def step(self, name: str):
        print(f"\n== {name}", flush=True)
        t0 = time.perf_counter()
        yield
        self.steps[name] = time.perf_counter() - t0
        print(f"   {name}: {self.steps[name]:.1f} s", flush=True)

    @property
    def total(self) -> float:
        return time.perf_counter() - self.start
