"""JEPA Policy as a LeRobot policy (the plugin ``lerobot_policy_jepa``), checked with LeRobot's own command lines.

    python scripts/interop_lerobot_policy.py --lerobot-venv .cache/interop/lerobot [--steps 200] [--episodes 10]

In order, each step timed (scripts/interop.sh runs it after building the venv):
  1. PushTStandard expert demonstrations written by LeRobot's own ``LeRobotDataset`` code in lerobot/pusht's
     layout (``scripts/interop_pusht_lerobot_peer.py``);
  2. ``lerobot-train --policy.type=jepa`` on it (``--steps``), and the MIP arm (``--policy.arm=mip``) briefly;
  3. ``lerobot-eval --policy.path=<its checkpoint> --env.type=pusht`` on gym-pusht (``--episodes``);
  4. the checkpoint LeRobot saved, loaded by our ``Policy.from_checkpoint``, and LeRobot's runtime
     (``interop_lerobot_policy_peer.py``) acting on the same ``--observations``: max |action difference| and
     max |z_hat difference|; ``jepa-policy eval`` runs it on our PushTStandard with the future latent scored;
  5. a checkpoint of ours (``jepa-policy train``) converted with ``python -m lerobot_policy_jepa.convert``: the same
     comparison, and ``lerobot-eval`` runs it.
Prints the numbers as JSON and writes them to WORK/lerobot_policy.json (with its wall time and the run id
scripts/interop.sh gives, ``INTEROP_RUN_ID``). Exit 1 when a check fails.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA_PEER = ROOT / "scripts" / "interop_pusht_lerobot_peer.py"
ACT_PEER = ROOT / "scripts" / "interop_lerobot_policy_peer.py"
TASK_STRING = "Push the T-shaped block onto the T-shaped target."
# the model of PushTStandard's cpu preset (jepa_policy/configs/PushTStandard.json), at the data's 96 px
CPU_MODEL = {"width": 64, "layers": 1, "heads": 4, "encoder_width": 8, "time_emb_dim": 48, "dropout": 0.0,
             "crop_ratio": 1.0, "image_norm": "dataset", "tau": 0.7}


def run(cmd: list[str], what: str, env: dict | None = None) -> tuple[subprocess.CompletedProcess, float]:
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{what} failed ({done.returncode}): {' '.join(cmd)}\n{done.stderr[-4000:]}")
    return done, round(seconds, 1)


def lerobot_env() -> dict:
    """LeRobot's command lines offline, single-threaded and reniced-friendly (the machine is shared)."""
    return {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1", "TOKENIZERS_PARALLELISM": "false"}


def write_dataset(py: str, work: Path, demos: int) -> tuple[Path, list[dict], float]:
    """PushTStandard demos -> lerobot/pusht's layout, written by LeRobot's LeRobotDataset."""
    from jepa_envs.tasks.pusht_expert import generate_demos

    start = time.perf_counter()
    episodes, _ = generate_demos(demos, seed=300, task="PushTStandard")
    src, root = work / "demos.npz", work / "pusht_lerobot"
    np.savez(src, frames=np.concatenate([e["obs"]["top_image"] for e in episodes]),
             state=np.concatenate([e["obs"]["agent_pos"] for e in episodes]).astype(np.float32),
             action=np.concatenate([e["actions"] for e in episodes]).astype(np.float32),
             episode_ends=np.cumsum([len(e["actions"]) for e in episodes]), task=TASK_STRING)
    run([py, str(DATA_PEER), "write", str(src), str(root)], "LeRobot's writer (lerobot/pusht layout)")
    return root, episodes, round(time.perf_counter() - start, 1)


def observations(episodes: list[dict], n: int, path: Path) -> Path:
    """The first ``n`` observations of the demonstrations, as gym-pusht hands them over (float64 agent_pos)."""
    frames, state, starts, t = [], [], [], 0
    for e in episodes:
        if t >= n:
            break
        starts.append(t)
        frames.append(e["obs"]["top_image"][:n - t])
        state.append(e["obs"]["agent_pos"][:n - t].astype(np.float64))
        t += len(frames[-1])
    if t < n:
        raise ValueError(f"the demonstrations hold {t} observations, fewer than --observations {n}")
    np.savez(path, pixels=np.concatenate(frames), agent_pos=np.concatenate(state), episode_starts=np.asarray(starts))
    return path


def lerobot_train(venv: Path, root: Path, out: Path, steps: int, batch: int, arm: str) -> dict:
    cmd = [str(venv / "bin" / "lerobot-train"), "--dataset.repo_id=local/pusht-layout", f"--dataset.root={root}",
           "--policy.type=jepa", f"--policy.arm={arm}", "--policy.device=cpu", "--policy.push_to_hub=false",
           *(f"--policy.{k}={v}" for k, v in CPU_MODEL.items()), "--policy.optimizer_lr=0.002",
           f"--policy.scheduler_warmup_steps={max(1, steps // 20)}", f"--policy.scheduler_decay_steps={steps}",
           f"--steps={steps}", f"--batch_size={batch}", "--num_workers=0", f"--log_freq={max(1, steps // 10)}",
           f"--save_freq={steps}", "--eval_freq=0", "--wandb.enable=false", "--seed=1", f"--output_dir={out}"]
    done, seconds = run(["nice", "-n", "19", *cmd], f"lerobot-train ({arm})", lerobot_env())
    log = done.stdout + done.stderr
    losses = [(int(float(s.replace("K", "e3"))), float(v)) for s, v in
              re.findall(r"step:(\S+) .*?loss:([-\d.e]+)", log)]
    checkpoint = out / "checkpoints" / f"{steps:06d}" / "pretrained_model"
    if not checkpoint.is_dir():
        raise RuntimeError(f"lerobot-train wrote no {checkpoint}:\n{log[-3000:]}")
    return {"command": " ".join(cmd), "steps": steps, "seconds": seconds, "losses": losses,
            "checkpoint": str(checkpoint)}


def lerobot_eval(venv: Path, policy: Path, out: Path, episodes: int) -> dict:
    cmd = [str(venv / "bin" / "lerobot-eval"), f"--policy.path={policy}", "--env.type=pusht",
           f"--eval.n_episodes={episodes}", f"--eval.batch_size={min(episodes, 10)}", "--policy.device=cpu",
           "--seed=100000", f"--output_dir={out}"]
    _, seconds = run(["nice", "-n", "19", *cmd], "lerobot-eval", lerobot_env())
    info = json.loads((out / "eval_info.json").read_text())["overall"]
    return {"command": " ".join(cmd), "seconds": seconds, "episodes": int(info["n_episodes"]),
            "pc_success": float(info["pc_success"]), "avg_max_reward": float(info["avg_max_reward"])}


def ours_act(checkpoint: str, obs_file: Path) -> dict:
    """Our runtime (``Policy.act``) on the observations, one at a time, reset at each episode start."""
    from jepa_policy.policy import Policy

    policy = Policy.from_checkpoint(checkpoint, detectors=False)
    data = np.load(obs_file)
    starts = set(data["episode_starts"].tolist())
    actions, z_hats, steps = [], [], []
    start = time.perf_counter()
    for t in range(len(data["pixels"])):
        if t in starts:
            policy.reset()
        before = policy.last_decision
        actions.append(policy.act({"top_image": data["pixels"][t], "agent_pos": data["agent_pos"][t]}))
        if policy.last_decision is not before:
            steps.append(t)
            if policy.last_decision.z_hat is not None:      # MIP predicts no future latent
                z_hats.append(policy.last_decision.z_hat)
    return {"actions": np.stack(actions), "z_hat": np.asarray(z_hats, dtype=np.float32),
            "decision_index": np.asarray(steps),
            "seconds": time.perf_counter() - start}


def compare_runtimes(venv: Path, checkpoint_ours: str, checkpoint_lerobot: str, obs_file: Path, out: Path) -> dict:
    """Our runtime on ``checkpoint_ours`` against LeRobot's on ``checkpoint_lerobot``, same observations."""
    run(["nice", "-n", "19", str(venv / "bin" / "python"), str(ACT_PEER), "act", checkpoint_lerobot, str(obs_file),
         str(out)], "LeRobot's runtime", lerobot_env())
    theirs = dict(np.load(out))
    ours = ours_act(checkpoint_ours, obs_file)
    same_grid = np.array_equal(ours["decision_index"], theirs["decision_index"])
    return {"observations": int(len(ours["actions"])), "decisions": int(len(ours["decision_index"])),
            "same_decision_steps": bool(same_grid),
            "max_abs_action_diff": float(np.abs(ours["actions"] - theirs["actions"]).max()),
            "max_abs_z_hat_diff": (float(np.abs(ours["z_hat"] - theirs["z_hat"]).max()) if same_grid and
                                   len(ours["z_hat"]) else None),
            "future_pairs_scored_in_lerobot": int(len(theirs["nmse"])),
            "median_nmse_in_lerobot": float(np.median(theirs["nmse"])) if len(theirs["nmse"]) else None,
            "seconds_ours": round(ours["seconds"], 1), "seconds_lerobot": round(float(theirs["seconds"]), 1)}


def our_eval(checkpoint: str, work: Path, episodes: int) -> dict:
    """``jepa-policy eval`` of a checkpoint LeRobot saved, on our PushTStandard, future latents scored."""
    records = work / "ours_eval.jsonl"
    cmd = [sys.executable, "-m", "jepa_policy.cli", "eval", "--checkpoint", checkpoint, "--episodes", str(episodes),
           "--num-envs", str(min(episodes, 4)), "--workers", "0", "--seed", "100000", "--out", str(records),
           "--no-progress"]
    _, seconds = run(["nice", "-n", "19", *cmd], "jepa-policy eval --checkpoint <LeRobot folder>",
                     {**os.environ, "OMP_NUM_THREADS": "1"})
    rows = [json.loads(line) for line in records.read_text().splitlines() if line.strip()]
    nmse = [d["nmse"] for r in rows for d in r.get("decisions", []) if d.get("nmse") is not None]
    return {"command": " ".join(cmd[2:]).replace("jepa_policy.cli", "jepa-policy"), "seconds": seconds,
            "episodes": len(rows), "successes": sum(bool(r.get("success")) for r in rows),
            "scored_decisions": len(nmse), "median_nmse": float(np.median(nmse)) if nmse else None}


def our_serve(checkpoint: str) -> dict:
    """``jepa-policy serve`` of a checkpoint LeRobot saved: it loads and binds (then is stopped)."""
    cmd = [sys.executable, "-m", "jepa_policy.cli", "serve", "--checkpoint", checkpoint, "--port", "0"]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        line = proc.stdout.readline().strip()
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    if "on ws://" not in line:
        raise RuntimeError(f"jepa-policy serve did not start: {line!r} {proc.stderr.read()[-2000:]}")
    return {"command": " ".join(cmd[2:]).replace("jepa_policy.cli", "jepa-policy"), "ready_line": line,
            "seconds_to_ready": round(time.perf_counter() - start, 1)}


def ours_to_lerobot(venv: Path, root: Path, work: Path, steps: int) -> tuple[str, str, dict]:
    """Train with our own trainer (the quick preset's schedule, the cpu model, 96 px), convert for LeRobot."""
    run_dir, converted = work / "ours_train", work / "ours_as_lerobot"
    model = json.dumps(CPU_MODEL)
    done, seconds = run(["nice", "-n", "19", sys.executable, "-m", "jepa_policy.cli", "train", "--task",
                         "PushTStandard", "--preset", "quick", "--image-size", "96", "--model", model, "--dataset",
                         str(root), "--steps", str(steps), "--warmup-steps", "1", "--eval-every", "0", "--out",
                         str(run_dir), "--no-progress"], "jepa-policy train",
                        {**os.environ, "OMP_NUM_THREADS": "1", "JEPA_DATA_CACHE": str(work / "cache")})
    checkpoint = json.loads(done.stdout.strip().splitlines()[-1])["checkpoint"]
    _, convert_s = run([str(venv / "bin" / "python"), "-m", "lerobot_policy_jepa.convert", checkpoint,
                        str(converted)], "python -m lerobot_policy_jepa.convert", lerobot_env())
    return checkpoint, str(converted), {"train_seconds": seconds, "convert_seconds": convert_s}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lerobot-venv", default=str(ROOT / ".cache" / "interop" / "lerobot"))
    parser.add_argument("--work", default="interop_out/lerobot_policy", help="scratch folder (replaced)")
    parser.add_argument("--demos", type=int, default=20, help="PushTStandard demonstrations in the dataset")
    parser.add_argument("--steps", type=int, default=200, help="lerobot-train steps of the JEPA arm")
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--episodes", type=int, default=10, help="lerobot-eval episodes on gym-pusht")
    parser.add_argument("--observations", type=int, default=1000, help="observations both runtimes act on")
    args = parser.parse_args()
    venv, work = Path(args.lerobot_venv).resolve(), Path(args.work).resolve()
    if not (venv / "bin" / "lerobot-train").exists():
        raise SystemExit(f"{venv} has no lerobot-train; build it with `make interop` (scripts/interop.sh)")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    started = time.perf_counter()
    result: dict = {"run_id": os.environ.get("INTEROP_RUN_ID")}   # scripts/interop.sh's, for its summary
    root, episodes, result["dataset_seconds"] = write_dataset(str(venv / "bin" / "python"), work, args.demos)
    result["dataset"] = {"episodes": len(episodes), "frames": int(sum(len(e["actions"]) for e in episodes))}
    obs_file = observations(episodes, args.observations, work / "observations.npz")
    result["train_jepa"] = lerobot_train(venv, root, work / "train_jepa", args.steps, args.batch_size, "jepa")
    result["train_mip"] = lerobot_train(venv, root, work / "train_mip", max(2, args.steps // 10), args.batch_size,
                                        "mip")
    checkpoint = result["train_jepa"]["checkpoint"]
    result["eval_lerobot"] = lerobot_eval(venv, Path(checkpoint), work / "eval_jepa", args.episodes)
    result["lerobot_to_ours"] = compare_runtimes(venv, checkpoint, checkpoint, obs_file,
                                                 work / "lerobot_acts_trained.npz")
    result["lerobot_to_ours"]["jepa_policy_eval"] = our_eval(checkpoint, work, 4)
    result["lerobot_to_ours"]["jepa_policy_serve"] = our_serve(checkpoint)
    result["mip_lerobot_to_ours"] = compare_runtimes(venv, result["train_mip"]["checkpoint"],
                                                     result["train_mip"]["checkpoint"], obs_file,
                                                     work / "lerobot_acts_mip.npz")
    ours, converted, times = ours_to_lerobot(venv, root, work, max(2, args.steps // 10))
    result["ours_to_lerobot"] = {**times, **compare_runtimes(venv, ours, converted, obs_file,
                                                                  work / "lerobot_acts_converted.npz")}
    result["ours_to_lerobot"]["lerobot_eval"] = lerobot_eval(venv, Path(converted), work / "eval_ours", 2)
    checks = [result["lerobot_to_ours"]["max_abs_action_diff"] == 0.0,
              result["lerobot_to_ours"]["max_abs_z_hat_diff"] == 0.0,
              result["ours_to_lerobot"]["max_abs_action_diff"] == 0.0,
              result["ours_to_lerobot"]["max_abs_z_hat_diff"] == 0.0,
              result["mip_lerobot_to_ours"]["max_abs_action_diff"] == 0.0,
              result["eval_lerobot"]["episodes"] == args.episodes]
    result["ok"] = all(checks)
    result["seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(result, indent=2))
    (work / "lerobot_policy.json").write_text(json.dumps(result, indent=2))
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
