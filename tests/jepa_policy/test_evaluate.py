"""Evaluation: the NMSE formula, the Table 6 protocols, and real rollouts with consistent per-decision records."""
import json

import numpy as np
import pytest

from jepa_policy.evaluate import reporting_protocols, residual_line, residualise_records
from monitor_service.scoring import nmse, nmse_rows


def test_nmse_matches_hand_computation():
    """The d_NMSE the records hold (``monitor_service.scoring.nmse_rows``; test_nmse_agreement.py: all agree)."""
    z = np.array([[3.0, 4.0], [0.0, 0.0]])
    z_hat = np.array([[3.0, 2.0], [1.0, -1.0]])
    rms0 = np.sqrt((9 + 16) / 2)
    expected0 = ((0 / rms0) ** 2 + (2 / rms0) ** 2) / 2
    expected1 = ((1 / 1e-6) ** 2 + (1 / 1e-6) ** 2) / 2  # zero target: the 1e-6 floor of Sec. 3.3
    np.testing.assert_allclose(nmse_rows(z_hat, z), [expected0, expected1], rtol=1e-12)
    assert nmse_rows(z[:1], z[:1])[0] == 0.0
    with pytest.raises(ValueError, match="equal shape"):
        nmse_rows(np.zeros((1, 3)), np.zeros((1, 4)))


def test_reporting_protocols_of_table_6():
    curve = [{"step": s, "success_rate": r} for s, r in
             [(30, 0.6), (10, 0.2), (20, 0.9), (40, 0.5), (50, 0.7), (60, 0.4), (70, 0.8)]]
    p = reporting_protocols(curve)
    assert p["best"] == 0.9
    assert p["last"] == 0.8                               # by step, not by list order
    assert p["mean_last5"] == pytest.approx(np.mean([0.6, 0.5, 0.7, 0.4, 0.8]))
    assert p["mean_all"] == pytest.approx(np.mean([0.2, 0.9, 0.6, 0.5, 0.7, 0.4, 0.8]))
    assert p["evaluations"] == 7
    with pytest.raises(ValueError, match="eval_every"):
        reporting_protocols([])


def synthetic_records(seeds, decisions: int = 6, seed: int = 0) -> list[dict]:
    """Episodes whose log NMSE follows log persistence NMSE with noise, as rollout records hold them."""
    rng = np.random.default_rng(seed)
    out = []
    for s in seeds:
        x = rng.normal(-2.0, 1.0, decisions)
        y = 0.3 + 0.7 * x + rng.normal(0.0, 0.5, decisions) + rng.normal(0.0, 1.0)   # + an episode's own shift
        out.append({"seed": int(s), "decisions": [{"step": 8 * i, "nmse": float(np.exp(yi)),
                                                   "nmse_persistence": float(np.exp(xi))}
                                                  for i, (xi, yi) in enumerate(zip(x, y))]
                   + [{"step": 8 * decisions, "nmse": None}]})
    return out


def _residuals(record) -> list[float]:
    return [d["nmse_residualised"] for d in record["decisions"] if d["nmse"] is not None]


def test_residualised_nmse_does_not_depend_on_the_runs_other_episodes():
    """One line fitted over the run gave an episode 0.090 with one companion and -0.611 with another."""
    calibration = synthetic_records(range(300_000, 300_040), seed=1)   # a held-out block of seeds
    episode, companion_a, companion_b = synthetic_records([100_000, 100_001, 100_002], seed=2)
    with_a = [json_copy(episode), json_copy(companion_a)]
    with_b = [json_copy(episode), json_copy(companion_b)]
    fit_a = residualise_records(with_a, calibration)
    residualise_records(with_b, calibration)
    assert _residuals(with_a[0]) == _residuals(with_b[0])
    line = residual_line(calibration)
    assert fit_a["slope"] == line["slope"] and fit_a["decisions"] == 40 * 6 and fit_a["episodes"] == 40
    assert fit_a["how"].startswith("fitted on the calibration split")
    # the line of a calibration split can be given as such (e.g. kept from an earlier run)
    again = [json_copy(episode)]
    residualise_records(again, line)
    assert _residuals(again[0]) == _residuals(with_a[0])
    with pytest.raises(ValueError, match="fewer than 3"):
        residualise_records([json_copy(episode)], synthetic_records([5], decisions=2))
    with pytest.raises(ValueError, match="intercept"):
        residualise_records([json_copy(episode)], {"how": "cross-fitted", "folds": {}})


def test_residualised_nmse_is_cross_fitted_without_a_calibration_split():
    """No episode is residualised on a line its own decisions helped fit: changing an episode's own scores moves
    only its own residuals by exactly that change."""
    records = synthetic_records(range(100_000, 100_012), seed=3)
    fit = residualise_records(records)
    assert fit["how"].startswith("cross-fitted") and sorted(fit["folds"]) == ["0", "1", "2", "3", "4"]
    changed = json_copy(records)
    for d in changed[0]["decisions"][:-1]:
        d["nmse"] *= np.e                                         # + 1 on the log scale
    residualise_records(changed)
    np.testing.assert_allclose(_residuals(changed[0]), np.array(_residuals(records[0])) + 1.0, atol=1e-12)
    fold0 = records[0]["seed"] % 5
    for before, after in zip(records[1:], changed[1:]):
        if before["seed"] % 5 == fold0:   # the same fold: fitted on the same other folds
            assert _residuals(after) == _residuals(before)
    # two episodes in different folds: each is residualised on the other's line, never on its own
    pair = synthetic_records([100_000, 100_001], seed=4)
    residualise_records(pair)
    own = residual_line([pair[1]])
    d = pair[0]["decisions"][0]
    assert d["nmse_residualised"] == pytest.approx(np.log(d["nmse"]) - own["intercept"]
                                                   - own["slope"] * np.log(d["nmse_persistence"]))
    assert residualise_records(synthetic_records([7], decisions=2)) is None


def json_copy(value):
    return json.loads(json.dumps(value))


@pytest.fixture(scope="module")
def checkpoint(pusht_demo_file, tmp_path_factory):
    import torch

    from jepa_envs.datasets.hdf5 import load_dataset
    from jepa_policy.train import load_config, train

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # shared 2-core machine: one thread runs faster than two oversubscribed ones
    demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
    out = tmp_path_factory.mktemp("eval_run")
    result = train(load_config("PushT", "quick", out_dir=str(out), steps=20), demos)
    yield result["checkpoint"]
    torch.set_num_threads(threads)


def test_rollouts_give_consistent_per_decision_nmse_records(checkpoint, tmp_path):
    import json

    from jepa_policy.evaluate import evaluate
    from jepa_policy.policy import Policy

    policy = Policy.from_checkpoint(checkpoint)
    events = []
    report = evaluate(policy, episodes=3, seed=7, num_envs=2, max_steps=30, keep_latents=True,
                      on_decision=events.append, video_dir=tmp_path / "video", out=tmp_path / "records.jsonl")
    records = report["records"]
    assert [r["seed"] for r in records] == [7, 8, 9] and [r["episode"] for r in records] == [0, 1, 2]
    assert report["success_rate"] == np.mean([r["success"] for r in records])
    assert report["mean_max_reward"] == pytest.approx(np.mean([r["max_reward"] for r in records]))
    for r in records:
        assert 0.0 <= r["max_reward"] <= 1.0                    # PushT reward = coverage of the goal
        steps = [d["step"] for d in r["decisions"]]
        assert steps == list(range(0, r["length"], 8))
        for d in r["decisions"]:
            assert d["target_step"] == d["step"] + 4
            if d["target_step"] <= r["length"]:
                z_hat, z = np.array(d["z_hat"]), np.array(d["z_real"])
                assert z.shape == (policy.model.future_dim,)
                assert d["nmse"] == pytest.approx(nmse(z_hat, z), rel=1e-9)
                assert d["nmse"] > 0
            else:
                assert d["nmse"] is None
    valid = [d["nmse"] for r in records for d in r["decisions"] if d["nmse"] is not None]
    assert report["mean_nmse"] == pytest.approx(np.mean(valid))
    # the persistence control (z_t taken as the prediction of z_{t+k}) and the NMSE residualised on it
    scored = [d for r in records for d in r["decisions"] if d["nmse"] is not None]
    pers = [d["nmse_persistence"] for d in scored]
    assert all(v >= 0 for v in pers) and report["mean_nmse_persistence"] == pytest.approx(np.mean(pers))
    # cross-fitted (no calibration split given): episode seed s is residualised on the line of the other seeds
    fit = report["residualised_fit"]
    assert fit["how"].startswith("cross-fitted") and set(fit["folds"]) == {str(r["seed"] % 5) for r in records}
    for r in records:
        others = [d for o in records if o["seed"] % 5 != r["seed"] % 5 for d in o["decisions"]
                  if d["nmse"] is not None]
        slope, intercept = np.polyfit(np.log([d["nmse_persistence"] for d in others]),
                                      np.log([d["nmse"] for d in others]), 1)
        own = [d for d in r["decisions"] if d["nmse"] is not None]
        np.testing.assert_allclose([d["nmse_residualised"] for d in own],
                                   [np.log(d["nmse"]) - intercept - slope * np.log(d["nmse_persistence"])
                                    for d in own], atol=1e-9)
    prediction = {(e.seed, e.step): e for e in events if e.kind == "prediction"}
    for r in records:
        for d in r["decisions"]:
            if d["nmse"] is not None:
                z_now = prediction[(r["seed"], d["step"])].z_now
                assert d["nmse_persistence"] == pytest.approx(nmse(z_now, np.array(d["z_real"])), rel=1e-9)
                # what a robot sends the monitor: the current latent too (its persistence baseline)
                np.testing.assert_array_equal(np.array(d["z_now"]), z_now)
    # the hook saw every prediction and every realized target, with the same numbers as the records
    realized = [e for e in events if e.kind == "realized"]
    assert len([e for e in events if e.kind == "prediction"]) == sum(len(r["decisions"]) for r in records)
    assert sorted(e.nmse for e in realized) == sorted(valid)
    lines = (tmp_path / "records.jsonl").read_text().splitlines()
    assert [json.loads(line)["seed"] for line in lines] == [7, 8, 9]
    assert len(list((tmp_path / "video").glob("*.gif"))) == 3
    # seeded: the same seeds give the same rollouts, whatever the number of parallel envs
    again = evaluate(policy, episodes=3, seed=7, num_envs=3, max_steps=30)["records"]
    assert [(r["success"], r["length"]) for r in again] == [(r["success"], r["length"]) for r in records]
    for r_again, r in zip(again, records):
        np.testing.assert_allclose([d["nmse"] or 0.0 for d in r_again["decisions"]],
                                   [d["nmse"] or 0.0 for d in r["decisions"]], rtol=1e-5)


def test_realized_latents_match_a_fresh_encoding_of_the_env_frame(checkpoint):
    import gymnasium as gym

    from jepa_policy.evaluate import env_kwargs_for, evaluate
    from jepa_policy.policy import Policy

    policy = Policy.from_checkpoint(checkpoint)
    report = evaluate(policy, episodes=1, seed=11, num_envs=1, max_steps=12, keep_latents=True)
    decision = report["records"][0]["decisions"][0]
    # replay the same episode by hand and encode frame t+k = 4 ourselves
    env = gym.make(policy.spec.env_id, **env_kwargs_for(policy.spec, policy.env_args))
    obs, _ = env.reset(seed=11)
    policy.reset()
    for _ in range(decision["target_step"]):
        obs, *_ = env.step(policy.act(obs))
    env.close()
    np.testing.assert_allclose(decision["z_real"], policy.encode_future(obs), rtol=1e-5, atol=1e-6)


def test_arms_without_a_future_head_record_decisions_without_nmse(pusht_demo_file, tmp_path):
    import torch

    from jepa_envs.datasets.hdf5 import load_dataset
    from jepa_policy.evaluate import evaluate
    from jepa_policy.policy import Policy
    from jepa_policy.train import load_config, train

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
        ckpt = train(load_config("PushT", "quick", arm="mip", out_dir=str(tmp_path), steps=2, warmup_steps=1),
                     demos)["checkpoint"]
        events = []
        report = evaluate(Policy.from_checkpoint(ckpt), episodes=1, seed=0, num_envs=1, max_steps=10,
                          on_decision=events.append)
    finally:
        torch.set_num_threads(threads)
    assert [d["step"] for d in report["records"][0]["decisions"]] == [0, 8]
    assert all(d["nmse"] is None for d in report["records"][0]["decisions"])
    assert report["mean_nmse"] is None and events == []


class _Saboteur:
    """Acts as the policy does, and at its ``at``-th action makes one pool worker fail (once)."""

    def __init__(self, policy, pool, at: int, command: str, payload):
        self._policy, self._pool, self._at, self._fault = policy, pool, at, (command, payload)
        self.calls = 0

    def __getattr__(self, name):
        return getattr(self._policy, name)

    def act(self, obs):
        self.calls += 1
        if self.calls == self._at:
            self._pool.inject(1, *self._fault)
        return self._policy.act(obs)


def _event_keys(events):
    return sorted((e.kind, e.seed, e.step) for e in events)


def test_the_pool_gives_identical_results_for_any_number_of_workers_and_reruns_a_failed_worker(checkpoint):
    from jepa_policy.evaluate import evaluate, make_pool
    from jepa_policy.policy import Policy

    policy = Policy.from_checkpoint(checkpoint)
    runs = {}
    for workers in (0, 1, 2):
        events = []
        report = evaluate(policy, episodes=5, seed=40, num_envs=2, max_steps=30, workers=workers,
                          keep_latents=True, on_decision=events.append)
        assert report["workers"] == workers and report["reruns"] == []
        runs[workers] = (report["records"], _event_keys(events))
    # bit-identical: same seeds, same batches of the policy, same order, whatever process stepped the envs
    assert runs[1] == runs[0] and runs[2] == runs[0]
    clean_records, clean_events = runs[0]

    # a worker that dies (as a segfault would) or stops answering is restarted, its round rerun, and said so
    for command, payload, reason in (("crash", 9, "exit code 9"), ("hang", 60.0, "hung")):
        pool = make_pool(policy, 2, workers=2, max_steps=30, timeout_s=3.0)
        try:
            first_pid = pool.describe()["pids"][1]
            events = []
            report = evaluate(_Saboteur(policy, pool, at=5, command=command, payload=payload), episodes=5, seed=40,
                              pool=pool, keep_latents=True, on_decision=events.append)
            assert pool.describe()["pids"][1] != first_pid
        finally:
            pool.close()
        assert len(report["reruns"]) == 1, report["reruns"]
        rerun = report["reruns"][0]
        assert rerun["worker"] == 1 and reason in rerun["reason"] and rerun["episodes"] == [0, 1]
        assert report["records"] == clean_records          # nothing lost, nothing changed
        assert _event_keys(events) == clean_events          # and no decision delivered twice


def test_a_worker_that_keeps_failing_ends_the_evaluation_with_the_reason(checkpoint):
    from jepa_policy.evaluate import evaluate, make_pool
    from jepa_policy.policy import Policy

    policy = Policy.from_checkpoint(checkpoint)

    class _AlwaysCrash(_Saboteur):
        def act(self, obs):
            self._pool.inject(1, "crash", 3)
            return self._policy.act(obs)

    with make_pool(policy, 2, workers=2, max_steps=10) as pool:
        with pytest.raises(RuntimeError, match=r"worker 1 failed: process ended \(exit code 3\).*failed 2 times"):
            evaluate(_AlwaysCrash(policy, pool, 0, "crash", 3), episodes=2, seed=0, pool=pool, max_reruns=1)


def test_saved_rollouts_carry_frames_actions_and_outcomes_into_a_lerobot_dataset(checkpoint, tmp_path):
    """``save_rollouts`` writes each evaluated episode (every frame rendered); exported to LeRobot v3.0 its outcome
    becomes next.success, and the import gives it back."""
    import h5py
    import pyarrow.parquet as pq

    from jepa_envs.datasets.lerobot import export_lerobot, import_lerobot
    from jepa_policy.evaluate import evaluate
    from jepa_policy.policy import Policy

    policy = Policy.from_checkpoint(checkpoint)
    report = evaluate(policy, episodes=3, seed=40, num_envs=2, max_steps=12, save_rollouts=tmp_path / "r.hdf5")
    with h5py.File(tmp_path / "r.hdf5") as f:
        demos = [f[f"data/demo_{i}"] for i in range(3)]
        assert [bool(d.attrs["success"]) for d in demos] == [r["success"] for r in report["records"]]
        assert [int(d.attrs["seed"]) for d in demos] == [r["seed"] for r in report["records"]]
        for d, r in zip(demos, report["records"]):
            images = d["obs/top_image"][()]
            assert len(images) == r["length"] and d["actions"].shape == (r["length"], 2)
            assert images.reshape(len(images), -1).any(axis=1).all(), "every frame rendered, none blank"
    export_lerobot(tmp_path / "r.hdf5", tmp_path / "ds")
    success = pq.read_table(tmp_path / "ds/data/chunk-000/file-000.parquet").column("next.success").to_pylist()
    assert sum(success) == sum(r["success"] for r in report["records"])
    import_lerobot(tmp_path / "ds", tmp_path / "back.hdf5", "PushT")
    with h5py.File(tmp_path / "back.hdf5") as f:
        assert [bool(f[f"data/demo_{i}"].attrs["success"]) for i in range(3)] == [r["success"] for r in
                                                                                   report["records"]]


def test_JEPA_POOL_TIMEOUT_S_reaches_the_pools_of_eval_train_and_bench(checkpoint, monkeypatch, capsys):
    """make_pool (eval, train's evaluations, protocols --select, bench rollouts, jepa-demo) passed a fixed 300 s
    that overrode the variable; it now leaves the limit to the pool: the variable, else derived from the task."""
    from jepa_policy.cli import main as policy_main
    from jepa_policy.evaluate import make_pool
    from jepa_policy.policy import Policy

    policy = Policy.from_checkpoint(checkpoint)
    monkeypatch.setenv("JEPA_POOL_TIMEOUT_S", "2.5")
    with make_pool(policy, 2, workers=1, max_steps=30) as pool:
        assert pool.describe()["step_timeout_s"] == [2.5]
    monkeypatch.setenv("JEPA_POOL_TIMEOUT_S", "soon")
    assert policy_main(["eval", "--checkpoint", str(checkpoint), "--episodes", "1", "--num-envs", "1",
                        "--workers", "1", "--max-steps", "5"]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(
        "jepa-policy eval: error: JEPA_POOL_TIMEOUT_S='soon' is not a number of seconds > 0")
