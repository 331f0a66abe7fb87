"""Synthetic monitored episodes from a known distribution, for the guarantee tests and the long-horizon study.

Per decision j (every ``interval`` env steps, its target ``horizon`` steps later) the log NMSE of a successful
episode is

    log e_j = base + phase_amplitude * sin(2 pi j / phase_period) + u + eps_j,

with an episode offset u ~ N(0, episode_sd^2) and AR(1) noise eps_j = rho eps_{j-1} + N(0, noise_sd^2 (1 - rho^2))
(stationary sd ``noise_sd``): decisions within an episode are correlated and the typical error changes with the
task phase, as on a real robot. A failure follows the same law until ``failure_onset`` x its length, then drifts
up linearly to ``drift`` (in log units) at its last decision.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from monitor_service.rules import EpisodeScores


@dataclass(frozen=True)
class SyntheticTask:
    base: float = -2.0
    phase_amplitude: float = 0.6
    phase_period: float = 20.0
    episode_sd: float = 0.15
    noise_sd: float = 0.3
    rho: float = 0.5
    drift: float = 1.5
    failure_onset: float = 0.5
    interval: int = 8
    horizon: int = 4


def log_nmse(task: SyntheticTask, decisions: int, failure: bool, rng: np.random.Generator) -> np.ndarray:
    """One episode's log NMSE per decision under ``task``."""
    j = np.arange(decisions)
    shocks = rng.normal(0.0, 1.0, decisions)
    shocks[1:] *= task.noise_sd * np.sqrt(1.0 - task.rho ** 2)
    shocks[0] *= task.noise_sd                      # the stationary start
    eps = lfilter([1.0], [1.0, -task.rho], shocks)  # eps_j = rho eps_{j-1} + shock_j
    log_e = task.base + task.phase_amplitude * np.sin(2 * np.pi * j / task.phase_period) + \
        rng.normal(0.0, task.episode_sd) + eps
    if failure:
        onset = int(task.failure_onset * decisions)
        ramp = np.clip((j - onset + 1) / max(1, decisions - onset), 0.0, 1.0)
        log_e = log_e + task.drift * ramp
    return log_e


def synthetic_episodes(n_success: int, n_failure: int, decisions: int, seed: int, task: SyntheticTask = SyntheticTask(),
                       group: str | None = None) -> list[EpisodeScores]:
    """``n_success`` successes then ``n_failure`` failures, each of ``decisions`` scored decisions."""
    rng = np.random.default_rng(seed)
    steps = np.arange(decisions, dtype=np.int64) * task.interval
    out = []
    for i in range(n_success + n_failure):
        failure = i >= n_success
        out.append(EpisodeScores(steps.copy(), np.exp(log_nmse(task, decisions, failure, rng)), steps + task.horizon,
                                 success=not failure, end_step=decisions * task.interval, group=group,
                                 episode=f"synthetic-{seed}-{i}"))
    return out


def mixed_length_episodes(n_success: int, n_failure: int, lengths: tuple[int, int], seed: int, sigma: float = 0.5,
                          shift: float = 0.7, interval: int = 8, horizon: int = 4) -> list[EpisodeScores]:
    """Episodes whose per-decision log NMSE does not depend on the decision index: iid N(-2, sigma^2), failures
    shifted up by ``shift``; each episode's length (scored decisions) uniform in ``lengths`` (the check of a
    false-alert promise per episode length, docs/monitor.md)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_success + n_failure):
        failure = i >= n_success
        n = int(rng.integers(lengths[0], lengths[1] + 1))
        steps = np.arange(n, dtype=np.int64) * interval
        out.append(EpisodeScores(steps, np.exp(rng.normal(-2.0, sigma, n) + (shift if failure else 0.0)),
                                 steps + horizon, success=not failure, end_step=n * interval,
                                 episode=f"mixed-{seed}-{i}"))
    return out
