"""Gaps in the decision stream: a skipped decision index is recorded per episode (API, metrics), the early score
comes only from the first five decisions of the episode's decision grid, and a changed early score is marked as
revised."""
import re

import numpy as np
import pytest
from monitor_testkit import post_batch, records_for_nmse, register_task


def _gaps_total(metrics: str) -> float:
    m = re.search(r'^jepa_monitor_decision_gaps_total\{robot="arm1",task="Square"\} ([0-9.]+)$', metrics, re.M)
    return float(m.group(1)) if m else 0.0


def _send(client, robot, episode, steps, values, rng, held_out=True):
    recs = records_for_nmse(episode, "Square", rng, values, steps, held_out=held_out)
    assert post_batch(client, robot, recs).status_code == 200


def test_a_skipped_decision_is_a_gap_and_holds_back_the_early_score(client, robot, operator):
    register_task(client, "Square")
    rng = np.random.default_rng(0)
    before = _gaps_total(client.get("/metrics", headers=operator).text)
    _send(client, robot, "g", [0, 1, 2, 4, 5], [0.1, 0.2, 0.3, 0.4, 0.5], rng)   # decision 3 skipped
    ep = client.get("/v1/episodes/g", headers=operator).json()
    assert ep["gaps"] == 1 and ep["gap_steps"] == [3] and ep["late_decisions"] == 0
    assert ep["early_score"] is None, "five decisions are scored, but not the first five of the grid"
    assert _gaps_total(client.get("/metrics", headers=operator).text) == before + 1
    _send(client, robot, "g", [3], [0.35], rng)   # it arrives late: the gap closes, the early score appears
    ep = client.get("/v1/episodes/g", headers=operator).json()
    assert ep["gaps"] == 0 and ep["gap_steps"] == [] and ep["late_decisions"] == 1
    assert ep["early_score"] == pytest.approx(0.3, rel=1e-4) and ep["early_revisions"] == 0
    listed = {e["id"]: e for e in client.get("/v1/episodes", headers=operator).json()}
    assert listed["g"]["gaps"] == 0 and listed["g"]["late_decisions"] == 1


def test_gaps_on_a_decision_grid_of_eight_steps(client, robot, operator):
    register_task(client, "Square")
    rng = np.random.default_rng(1)
    _send(client, robot, "g8", [0, 8, 16, 40, 48, 72], [0.1] * 6, rng)
    ep = client.get("/v1/episodes/g8", headers=operator).json()
    assert ep["gaps"] == 4 and ep["gap_steps"] == [24, 32, 56, 64] and ep["early_score"] is None


def test_an_early_score_changed_by_a_late_decision_is_marked_revised(client, robot, operator):
    register_task(client, "Square")
    rng = np.random.default_rng(2)
    _send(client, robot, "r", [8, 16, 24, 32, 40], [1.0, 2.0, 3.0, 4.0, 5.0], rng)
    ep = client.get("/v1/episodes/r", headers=operator).json()
    assert ep["early_score"] == pytest.approx(3.0, rel=1e-4) and ep["early_revisions"] == 0
    # the episode's first decision (step 0) arrives last: the grid starts at 0, the first five are 0..32
    _send(client, robot, "r", [0], [0.5], rng)
    ep = client.get("/v1/episodes/r", headers=operator).json()
    assert ep["early_score"] == pytest.approx(2.0, rel=1e-4) and ep["early_revisions"] == 1
    assert ep["late_decisions"] == 1 and ep["gaps"] == 0


def test_a_step_sent_far_ahead_costs_no_memory_for_its_gap():
    """A robot key sent decisions at steps 0, 1 and then 2**30: the server built the whole grid of missing steps
    (2**30 ints) and was OOM-killed at 22.9 GB. The gap count is exact, the listed steps the first 50, and the
    work is bounded by the decisions received, for a new far step and for a grid recomputed from scratch."""
    import tracemalloc

    from monitor_service.ingest.state import GAP_STEPS_SHOWN, EpisodeState

    far = 10 ** 7   # enough to measure (the old path: a 10-million-element list, hundreds of MB)
    ep = EpisodeState(id="e", task="t", robot="r", checkpoint=None, group=None, held_out=False)
    tracemalloc.start()
    try:
        for step in (0, 1, far):
            ep.decisions[step] = None
            ep.add_step(step)
        ep.decisions[far + 3] = None
        ep.add_step(far + 3)          # cadence unchanged; and off the grid: recomputed from scratch
        ep.decisions[far + 5] = None
        ep.count_gaps()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert ep.gaps == far + 5 + 1 - 5
    assert ep.gap_steps == list(range(2, 2 + GAP_STEPS_SHOWN))
    assert peak < 1_000_000, f"{peak / 1e6:.0f} MB for the gap of one far step"


def test_a_decision_at_the_largest_step_is_answered_and_counted(client, robot, operator):
    register_task(client, "Square")
    rng = np.random.default_rng(3)
    _send(client, robot, "far", [0, 1], [0.1, 0.2], rng)
    _send(client, robot, "far", [2 ** 30], [0.3], rng)
    ep = client.get("/v1/episodes/far", headers=operator).json()
    assert ep["gaps"] == 2 ** 30 - 2 and ep["gap_steps"][:3] == [2, 3, 4] and len(ep["gap_steps"]) == 50
