"""robomimic's own BC-RNN (image) as the peer of JEPA Policy and MIP on Lift (issue 49, item 3).

robomimic 0.3.0's ``train.py`` trains its standard image BC-RNN (the values of its ``generate_paper_configs.py``
for Lift, proficient-human, image) on the pick job's 200 scripted Lift demonstrations within the wall-clock budget
of our longest Lift arm (27 minutes of one core), and robomimic's own ``RolloutPolicy`` is evaluated on
``gym.make("JEPA/Lift-v0")`` with the seeds, step limit and success criterion of our arms (200 episodes from
200,000; ``jepa_policy/demo/pick.py``). The steps:

1. ``convert``: the demonstrations (``demo_out/Lift/data/lift_train_200demos_64px.hdf5``, already robomimic's
   layout) copied with one change: the action's position (our actions are absolute OSC goals: position, 6-D
   rotation, gripper) mapped from the demonstrations' range onto [-1, 1], because robomimic 0.3.0 squashes every
   GMM mean with tanh and would never reach the table's height (z about 1.0 m). The rotation and gripper are in
   [-1, 1] already and stay as they are. The range is kept in the file (``data`` attrs) and undone at evaluation;
2. ``train``: the config built by robomimic's own functions (``modify_config_for_default_image_exp``,
   ``modify_config_for_dataset(.., "lift", "ph", "image")``, ``modify_bc_rnn_config_for_dataset``), changed only
   where our data or the budget need it (``DEVIATIONS``), then ``python -m robomimic.scripts.train`` in
   robomimic's venv, one thread (``OMP_NUM_THREADS=1``), stopped when the budget is spent; robomimic saves a
   checkpoint every epoch (``EPOCH_STEPS`` gradient steps), and the last one saved within the budget is evaluated;
3. ``heldout``: the RolloutPolicy's actions along the pick job's 20 held-out scripted demonstrations against the
   recorded ones (position, orientation and gripper errors, as the pick job reports them for our arms);
4. ``eval``: robomimic's ``policy_from_checkpoint`` -> ``RolloutPolicy`` in its venv, fed our env's observations
   through robomimic's ``process_obs_dict`` (what its own ``EnvRobosuite`` does), on the 200 seeds, one episode
   after the other, appended to ``demo_out/Lift-bcrnn/eval_final.jsonl`` so that a stopped evaluation resumes; the
   first observation of demo_0's seed is first checked to equal demo_0's (no convention mismatch);
5. ``summary``: ``docs/results/lift-bcrnn/`` (``summary.json``, ``records_final.jsonl.gz``, ``config.json``) from
   what is evaluated so far (``complete`` says whether all 200 seeds are).

robomimic's venv is the one ``make interop`` builds (``scripts/interop.sh``: ``.cache/interop/robomimic``).
Its ``train.py`` and our env need four more packages there, installed without changing any installed version::

    env PIP_FIND_LINKS= PIP_CONFIG_FILE=/dev/null .cache/interop/robomimic/bin/pip install \\
        psutil imageio==2.38.2 tensorboardX gymnasium==1.4.0

Commands (27 minutes of training; at load 1-9 on 2 cores a failed episode's 400 steps took 45-204 s, median 73 s,
so 200 of them take about 4 hours; reruns reuse what exists)::

    nice -n 5 python scripts/robomimic_bcrnn.py all          # convert, train, heldout, eval, summary
    nice -n 5 python scripts/robomimic_bcrnn.py eval         # resume the evaluation, then the summary
    python scripts/robomimic_bcrnn.py eval --checkpoint PATH --name NAME   # another checkpoint
    python scripts/robomimic_bcrnn.py summary                # docs/results/lift-bcrnn/ from what is evaluated

Run it with this project's Python (the one ``jepa-demo`` runs with); it starts robomimic's venv for the steps that
need robomimic.
"""
from __future__ import annotations

import argparse
import gzip
import json
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
VENV_PYTHON = ROOT / ".cache/interop/robomimic/bin/python"
SOURCE = ROOT / "demo_out/Lift/data/lift_train_200demos_64px.hdf5"
WORK = ROOT / "demo_out/Lift-bcrnn"
DATASET = WORK / "lift_200demos_64px_robomimic.hdf5"
HELD_OUT = ROOT / "demo_out/Lift/data/lift_heldout_20demos_64px.hdf5"   # the pick job's 20 held-out demonstrations
CONFIG = WORK / "bc_rnn_image.json"
RESULTS = ROOT / "docs/results/lift-bcrnn"
EXPERIMENT = "lift_bc_rnn_image"

BUDGET_S = 27 * 60        # our longest Lift arm at 4,000 steps (JEPA, 26.8 min on one core)
EPOCH_STEPS = 10          # gradient steps per robomimic epoch: a checkpoint every epoch (2-2.5 min of one core)
MAX_EPOCHS = 10_000       # never reached: the budget stops the run
EVAL_SEED, EPISODES = 200_000, 200
IMAGE_SIZE = 64
CROP = 58                 # robomimic crops 84 px to 76 (0.905); 64 px to 58 keeps the ratio
POSITION = slice(0, 3)    # the action's absolute position (x, y, z); then 6-D rotation and gripper, in [-1, 1]

DEVIATIONS = {
    "train.data / output_dir / experiment.name": "our converted demonstrations and our output folder",
    "train.cuda: true -> false": "trained on one CPU core, as our arms are",
    "train.num_data_workers: 2 -> 0": "one core: data workers would be a second and third process",
    "experiment.validate: true -> false (no train/valid filter keys)": "all 200 demonstrations train, as for our "
                                                                       "arms; nothing selects on validation",
    "experiment.rollout.enabled: true -> false": "evaluated afterwards on our env and seeds; robomimic's rollouts "
                                                 "every 20 epochs would spend the budget",
    "experiment.epoch_every_n_steps: 500 -> 10, save.every_n_epochs: 20 -> 1, train.num_epochs: 600 -> 10000":
        "a checkpoint every 10 gradient steps (one step takes 10-15 s on one core); the 27-minute budget, not "
        "the epoch count, ends the run",
    "observation.encoder.rgb.obs_randomizer_kwargs.crop_height/width: 76 -> 58": "our images are 64 px, not 84",
    "actions: 10-D absolute (position, 6-D rotation, gripper), position mapped onto [-1, 1]":
        "our env takes absolute OSC goals (robomimic's datasets: 7-D deltas in [-1, 1]); robomimic 0.3.0 "
        "tanh-squashes GMM means",
}


def log(msg: str) -> None:
    print(f"[bcrnn] {msg}", flush=True)


# ----------------------------------------------------------------------------- 1. conversion

def convert(source: Path = SOURCE, dest: Path = DATASET) -> Path:
    """Copy ``source`` with the action's position mapped from its range over all demonstrations onto [-1, 1]."""
    import h5py

    if dest.exists():
        log(f"reusing {dest}")
        return dest
    if not source.exists():
        raise FileNotFoundError(f"{source} is missing: `jepa-demo --task Lift` writes it (its first step)")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_suffix(".tmp.hdf5")
    with h5py.File(source, "r") as src, h5py.File(tmp, "w") as out:
        demos = list(src["data"].keys())
        positions = np.concatenate([src[f"data/{d}/actions"][:, POSITION] for d in demos])
        low, high = positions.min(axis=0), positions.max(axis=0)
        data = out.create_group("data")
        for key, value in src["data"].attrs.items():
            data.attrs[key] = value
        data.attrs["action_position_low"] = low
        data.attrs["action_position_high"] = high
        for d in demos:
            src.copy(src[f"data/{d}"], data, name=d)
            actions = np.array(src[f"data/{d}/actions"])
            actions[:, POSITION] = scale_position(actions[:, POSITION], low, high)
            data[d]["actions"][...] = actions
    tmp.replace(dest)
    log(f"{len(demos)} demonstrations -> {dest} (position range {low.round(4).tolist()} .. {high.round(4).tolist()})")
    return dest


def scale_position(position: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    return (2.0 * (position - low) / (high - low) - 1.0).astype(np.float32)


def unscale_position(scaled: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    return (low + (np.asarray(scaled, np.float64) + 1.0) * (high - low) / 2.0).astype(np.float32)


# ----------------------------------------------------------------------------- 2. training

def venv(*args: str, **kwargs) -> subprocess.CompletedProcess:
    if not VENV_PYTHON.exists():
        raise FileNotFoundError(f"robomimic's venv is missing ({VENV_PYTHON}): `make interop` builds it")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    return subprocess.run([str(VENV_PYTHON), *args], env=env, check=True, **kwargs)


def write_config(dataset: Path = DATASET, path: Path = CONFIG) -> Path:
    """Run in robomimic's venv: robomimic's own image BC-RNN config for Lift (ph, image), then DEVIATIONS."""
    from robomimic.config import config_factory
    import robomimic.scripts.generate_paper_configs as paper

    config = config_factory("bc")
    config = paper.modify_config_for_default_image_exp(config)
    config = paper.modify_config_for_dataset(config, "lift", "ph", "image", str(WORK))
    config = paper.modify_bc_rnn_config_for_dataset(config, "lift", "ph", "image")
    with config.values_unlocked():
        config.experiment.name = EXPERIMENT
        config.train.data = str(dataset)
        config.train.output_dir = str(WORK / "trained_models")
        config.train.cuda = False
        config.train.num_data_workers = 0
        config.train.hdf5_load_next_obs = False   # robomimic's BC default already; our file holds no next_obs
        config.experiment.validate = False
        config.train.hdf5_filter_key = None
        config.train.hdf5_validation_filter_key = None
        config.experiment.rollout.enabled = False
        config.experiment.epoch_every_n_steps = EPOCH_STEPS
        config.experiment.save.every_n_epochs = 1
        config.train.num_epochs = MAX_EPOCHS
        config.observation.encoder.rgb.obs_randomizer_kwargs.crop_height = CROP
        config.observation.encoder.rgb.obs_randomizer_kwargs.crop_width = CROP
    path.parent.mkdir(parents=True, exist_ok=True)
    config.dump(str(path))
    return path


def train(budget_s: float = BUDGET_S) -> dict:
    """robomimic's train.py in its venv, stopped once ``budget_s`` of wall clock is spent; the load average
    sampled every 30 s."""
    run_dir = WORK / "trained_models" / EXPERIMENT
    record = WORK / "training.json"
    if record.exists():
        log(f"reusing the finished training run ({record})")
        return json.loads(record.read_text())
    venv(str(Path(__file__).resolve()), "_config")
    if run_dir.exists():   # train.py asks before overwriting an experiment (a run cut short before)
        shutil.rmtree(run_dir)
    log_path = WORK / "train.log"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    loads = [{"t": 0.0, "loadavg": Path("/proc/loadavg").read_text().split()[:3]}]
    started = time.time()
    with open(log_path, "w") as out:
        proc = subprocess.Popen([str(VENV_PYTHON), "-m", "robomimic.scripts.train", "--config", str(CONFIG)],
                                stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        log(f"train.py (pid {proc.pid}) for {budget_s / 60:.1f} min; log {log_path}")
        next_sample = started + 30
        while proc.poll() is None and time.time() - started < budget_s:
            time.sleep(1)
            if time.time() >= next_sample:
                loads.append({"t": round(time.time() - started, 1),
                              "loadavg": Path("/proc/loadavg").read_text().split()[:3]})
                next_sample += 30
        stopped_by_budget = proc.poll() is None
        if stopped_by_budget:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
    wall_s = time.time() - started
    text = log_path.read_text()
    if not stopped_by_budget:
        raise RuntimeError(f"robomimic's train.py ended by itself before the budget (exit {proc.returncode}): "
                           f"see {log_path}")
    checkpoints = []
    for ckpt in sorted(run_dir.glob("*/models/model_epoch_*.pth"), key=lambda p: p.stat().st_mtime):
        epoch = int(re.search(r"model_epoch_(\d+)\.pth$", ckpt.name).group(1))
        checkpoints.append({"path": str(ckpt.relative_to(ROOT)), "epoch": epoch, "steps": epoch * EPOCH_STEPS,
                            "wall_s": round(ckpt.stat().st_mtime - started, 1)})
    if not checkpoints:
        raise RuntimeError(f"no checkpoint was saved within the budget: see {log_path}")
    epochs_done = max(int(e) for e in re.findall(r"^Train Epoch (\d+)$", text, flags=re.M))
    losses = [float(x) for x in re.findall(r'"Loss": ([-0-9.e]+)', text)]
    result = {"budget_s": budget_s, "wall_s": round(wall_s, 1), "epochs_completed": epochs_done,
              "gradient_steps": epochs_done * EPOCH_STEPS, "epoch_every_n_steps": EPOCH_STEPS,
              "checkpoints": checkpoints, "final_checkpoint": checkpoints[-1], "loadavg_samples": loads,
              "train_loss_per_epoch": losses, "threads": 1}
    record.write_text(json.dumps(result, indent=1))
    log(f"{epochs_done} epochs = {epochs_done * EPOCH_STEPS} gradient steps in {wall_s / 60:.1f} min; "
        f"last checkpoint epoch {checkpoints[-1]['epoch']} at {checkpoints[-1]['wall_s'] / 60:.1f} min")
    return result


# ----------------------------------------------------------------------------- 3. evaluation (robomimic's venv)

def first_observation_check(env, obs_keys: list[str]) -> dict:
    """Our env's first observation of demo_0's seed against what demo_0 holds (the same arrays, or a mismatch
    of conventions that would make any success rate meaningless)."""
    import h5py

    with h5py.File(DATASET, "r") as f:
        demo = f["data/demo_0"]
        obs, _ = env.reset(seed=int(demo.attrs["seed"]))
        diffs = {k: float(np.abs(np.asarray(obs[k], np.float64) - demo[f"obs/{k}"][0]).max()) for k in obs_keys}
        shapes = {k: [list(np.shape(obs[k])), str(np.asarray(obs[k]).dtype),
                      list(demo[f"obs/{k}"].shape[1:]), str(demo[f"obs/{k}"].dtype)] for k in obs_keys}
    if any(d > 0 for d in diffs.values()):
        raise RuntimeError(f"our env's first observation differs from demo_0's: {diffs}")
    return {"max_abs_difference": diffs, "shape_dtype_env_vs_demo": shapes}


def _load_rollout_policy(checkpoint: Path):
    """Run in robomimic's venv: robomimic's ``RolloutPolicy`` of ``checkpoint`` on one CPU thread, its observation
    keys, and the converted file's ``env_args`` and position range (to undo ``scale_position``)."""
    import h5py
    import torch
    import robomimic.utils.file_utils as FileUtils

    torch.set_num_threads(1)
    policy, ckpt = FileUtils.policy_from_checkpoint(ckpt_path=str(checkpoint), device=torch.device("cpu"),
                                                    verbose=False)
    with h5py.File(DATASET, "r") as f:
        env_args = json.loads(f["data"].attrs["env_args"])
        low = np.asarray(f["data"].attrs["action_position_low"])
        high = np.asarray(f["data"].attrs["action_position_high"])
    return policy, list(ckpt["shape_metadata"]["all_obs_keys"]), env_args, low, high


def evaluate(checkpoint: Path, out: Path, seed: int = EVAL_SEED, episodes: int = EPISODES) -> None:
    """Run in robomimic's venv: rollouts of robomimic's RolloutPolicy on our env, one JSON line each, appended to
    ``out`` (its first line: the first-observation check); seeds already in ``out`` are skipped, so a stopped
    evaluation resumes where it stopped."""
    import gymnasium as gym
    import robomimic.utils.obs_utils as ObsUtils

    import jepa_envs  # noqa: F401  (registers JEPA/Lift-v0)
    from jepa_envs.tasks.outcomes import failure_kind_name

    policy, obs_keys, env_args, low, high = _load_rollout_policy(checkpoint)
    env = gym.make("JEPA/Lift-v0", env_args=env_args, image_size=IMAGE_SIZE)
    done = set()
    if out.exists():
        lines = [json.loads(x) for x in out.read_text().splitlines()]
        if lines[0]["checkpoint"] != str(checkpoint):
            raise RuntimeError(f"{out} holds episodes of {lines[0]['checkpoint']}, not {checkpoint}: remove it first")
        done = {r["seed"] for r in lines[1:]}
    else:
        check = first_observation_check(env, obs_keys)
        out.write_text(json.dumps({"check": check, "obs_keys": obs_keys, "checkpoint": str(checkpoint)}) + "\n")
    with open(out, "a") as fh:
        for s in range(seed, seed + episodes):
            if s in done:
                continue
            started = time.perf_counter()
            obs, info = env.reset(seed=s)
            policy.start_episode()
            success, t, kind = False, 0, int(info["failure_kind"])
            while True:
                action = np.asarray(policy(ob=ObsUtils.process_obs_dict({k: obs[k] for k in obs_keys})), np.float32)
                action[POSITION] = unscale_position(action[POSITION], low, high)
                obs, _, terminated, truncated, info = env.step(action)
                t += 1
                success |= bool(info["is_success"])
                kind = int(info["failure_kind"])
                if terminated or truncated:
                    break
            fh.write(json.dumps({"seed": s, "success": success, "length": t, "arm": "bc_rnn",
                                 "failure_kind": None if success else failure_kind_name(kind),
                                 "wall_s": round(time.perf_counter() - started, 2),
                                 "loadavg": Path("/proc/loadavg").read_text().split()[:3]}) + "\n")
            fh.flush()
            print(f"seed {s}: {'success' if success else 'failure'} in {t} steps", flush=True)
    env.close()


def heldout_actions(checkpoint: Path, out: Path, dataset: Path = HELD_OUT) -> None:
    """Run in robomimic's venv: the RolloutPolicy's actions along each held-out scripted demonstration (its
    recorded observations, the LSTM's state carried as in a rollout) beside the recorded actions (``out``, npz)."""
    import h5py
    import robomimic.utils.obs_utils as ObsUtils

    policy, obs_keys, _, low, high = _load_rollout_policy(checkpoint)
    predicted, recorded = [], []
    with h5py.File(dataset, "r") as f:
        for name in f["data"]:
            demo = f[f"data/{name}"]
            obs = {k: demo[f"obs/{k}"][:] for k in obs_keys}
            policy.start_episode()
            for t in range(len(demo["actions"])):
                action = np.asarray(policy(ob=ObsUtils.process_obs_dict({k: v[t] for k, v in obs.items()})))
                action[POSITION] = unscale_position(action[POSITION], low, high)
                predicted.append(action)
            recorded.append(demo["actions"][:])
    np.savez(out, predicted=np.stack(predicted), recorded=np.concatenate(recorded))


def heldout_errors(checkpoint: Path, out: Path) -> dict:
    """``heldout_actions`` in robomimic's venv, then the errors in the terms of the pick job's ``action_errors``:
    position (cm), orientation (degrees), gripper sign agreement."""
    from jepa_envs.tasks.rotations import rot6d_to_matrix

    if not out.exists():
        raw = out.with_suffix(".npz")
        venv(str(Path(__file__).resolve()), "_heldout", str(checkpoint.resolve()), str(raw))
        arrays = np.load(raw)
        predicted, recorded = arrays["predicted"].astype(np.float64), arrays["recorded"].astype(np.float64)
        pos = np.linalg.norm(predicted[:, :3] - recorded[:, :3], axis=1) * 100
        rel = np.einsum("nij,nik->njk", rot6d_to_matrix(predicted[:, 3:9]), rot6d_to_matrix(recorded[:, 3:9]))
        angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
        grip = np.sign(predicted[:, 9]) == np.sign(recorded[:, 9])
        out.write_text(json.dumps({
            "checkpoint": str(checkpoint.resolve().relative_to(ROOT)), "dataset": str(HELD_OUT.relative_to(ROOT)),
            "steps": int(len(recorded)),
            "position_cm": {"median": float(np.median(pos)), "p90": float(np.percentile(pos, 90))},
            "orientation_deg": {"median": float(np.median(angle)), "p90": float(np.percentile(angle, 90))},
            "gripper_agreement": float(grip.mean())}, indent=1) + "\n")
    return json.loads(out.read_text())


def run_eval(checkpoint: Path, out: Path) -> list[dict]:
    """``evaluate`` in robomimic's venv (resuming ``out``); its lines."""
    venv(str(Path(__file__).resolve()), "_eval", str(checkpoint.resolve()), str(out))
    return [json.loads(x) for x in out.read_text().splitlines()]


# ----------------------------------------------------------------------------- 4. summary

def summarize(training: dict, evaluations: dict[str, list[dict]]) -> dict:
    from jepa_policy.demo.pick import rate

    RESULTS.mkdir(parents=True, exist_ok=True)
    shutil.copy(CONFIG, RESULTS / "config.json")
    results = {}
    for name, lines in evaluations.items():
        head, records = lines[0], lines[1:]
        eval_loads = [float(r["loadavg"][0]) for r in records]
        results[name] = {**rate(records), "checkpoint": str(Path(head["checkpoint"]).relative_to(ROOT)),
                         "seeds_evaluated": [records[0]["seed"], records[-1]["seed"]] if records else None,
                         "complete": len(records) == EPISODES,
                         "eval_wall_s": round(sum(r["wall_s"] for r in records), 1),
                         "eval_load_1min": {"min": min(eval_loads), "median": float(np.median(eval_loads)),
                                            "max": max(eval_loads)} if records else None}
        with gzip.open(RESULTS / f"records_{name}.jsonl.gz", "wt") as fh:
            fh.writelines(json.dumps(r) + "\n" for r in records)
    loads = [float(s["loadavg"][0]) for s in training["loadavg_samples"]]
    summary = {
        "task": "Lift", "policy": "robomimic 0.3.0 BC-RNN (image), its own train.py and RolloutPolicy",
        "demos": {"file": str(SOURCE.relative_to(ROOT)), "episodes": 200, "image_size": IMAGE_SIZE},
        "seeds": {"from": EVAL_SEED, "episodes": EPISODES},
        "training": {k: v for k, v in training.items() if k not in ("loadavg_samples", "train_loss_per_epoch")},
        "training_load_1min": {"min": min(loads), "median": float(np.median(loads)), "max": max(loads)},
        "training_loadavg_samples": training["loadavg_samples"],
        "train_loss_per_epoch": training["train_loss_per_epoch"],
        "deviations_from_robomimic_config": DEVIATIONS,
        "results": results,
        "heldout_action_errors": {p.stem.removeprefix("heldout_"): json.loads(p.read_text())
                                  for p in sorted(WORK.glob("heldout_*.json"))},
        "first_observation_check": evaluations[next(iter(evaluations))][0]["check"],
    }
    (RESULTS / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    log(f"-> {RESULTS / 'summary.json'}")
    return summary


def existing_evaluations() -> dict[str, list[dict]]:
    return {p.stem.removeprefix("eval_"): [json.loads(x) for x in p.read_text().splitlines()]
            for p in sorted(WORK.glob("eval_*.jsonl"))}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=["all", "convert", "train", "heldout", "eval", "summary", "_config",
                                                    "_eval", "_heldout"])
    parser.add_argument("rest", nargs="*", help=argparse.SUPPRESS)
    parser.add_argument("--checkpoint", type=Path, help="eval: this checkpoint instead of the last in the budget")
    parser.add_argument("--name", default="final", help="eval: the results' name (records_NAME.jsonl.gz)")
    args = parser.parse_args(argv)
    if args.step == "_config":
        write_config()
        return
    if args.step == "_eval":
        evaluate(Path(args.rest[0]), Path(args.rest[1]))
        return
    if args.step == "_heldout":
        heldout_actions(Path(args.rest[0]), Path(args.rest[1]))
        return
    convert()
    if args.step == "convert":
        return
    training = train()
    if args.step == "train":
        return
    checkpoint = args.checkpoint or ROOT / training["final_checkpoint"]["path"]
    if args.step in ("all", "heldout"):
        heldout_errors(checkpoint, WORK / f"heldout_{args.name}.json")
    if args.step in ("all", "eval"):
        run_eval(checkpoint, WORK / f"eval_{args.name}.jsonl")
    summarize(training, existing_evaluations())


if __name__ == "__main__":
    main()
