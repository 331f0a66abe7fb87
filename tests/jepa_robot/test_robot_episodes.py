import json

import numpy as np
import pytest

from jepa_robot.episodes import EpisodeRecord, latency_stats, load_episode


def test_latency_stats_match_numpy_and_drop_first_chunk():
    lat = [0.5, 0.010, 0.020, 0.030, 0.040, 0.100]
    stats = latency_stats(lat)
    assert stats["count"] == 5
    assert stats["median_ms"] == pytest.approx(np.median(lat[1:]) * 1e3)
    assert stats["p95_ms"] == pytest.approx(np.percentile(lat[1:], 95) * 1e3)
    assert latency_stats(lat, skip_first=False)["count"] == 6
    assert latency_stats([])["median_ms"] is None


def test_record_round_trip(tmp_path):
    rec = EpisodeRecord(task="Cabinet", chunk_budget=60, action_dim=3, manifest={"checkpoint": "ckpt-60k"})
    obs = {"base_image": np.full((8, 8, 3), 7, np.uint8), "robot0_eef_pos": np.ones(3, np.float32)}
    rec.add_decision_frame(obs)
    rec.chunks = 1
    rec.chunk_latency_s += [0.02]
    rec.add_action(np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 2.5]))
    rec.add_action(np.array([9.0, 9.0, 9.0]), None)
    rec.add_safety_event(1, {"refused": True, "violations": ["jump"]})
    with pytest.raises(ValueError, match="outcome must be one of"):
        rec.finish("maybe")
    rec.finish("success", "operator confirmed")
    path = rec.save(tmp_path)
    manifest, arrays = load_episode(path)
    assert manifest["is_success"] and manifest["manifest"]["checkpoint"] == "ckpt-60k"
    assert manifest["steps"] == 1 and manifest["safety_events"][0]["violations"] == ["jump"]
    assert np.array_equal(arrays["obs/base_image"][0], obs["base_image"])
    assert np.array_equal(arrays["actions_executed"][0], [1.0, 2.0, 2.5])
    assert np.isnan(arrays["actions_executed"][1]).all() and arrays["actions_requested"][1][0] == 9.0
    assert json.loads(path.read_text())["arrays"].endswith(".h5")
