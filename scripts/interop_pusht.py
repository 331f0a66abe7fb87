"""`make interop`, gym-pusht part: our standard PushT (``JEPA/PushTStandard-v0``) checked step for step against
gym-pusht 0.1.8 itself, and its step speed beside gym-pusht's in the same run.

gym-pusht pins pymunk < 7, so it runs in a venv of its own (scripts/interop.sh builds it) through
scripts/interop_pusht_peer.py; our variant runs twice: with this project's pymunk (7.x) and, inside gym-pusht's
venv, with pymunk 6, which tells a difference of pymunk versions from one of ours.

For each seed (0 .. seeds-1) both envs are reset with that seed and then take the same ``steps`` actions: uniform
random targets, and the scripted expert's targets (planned on our env, held at the last target once it succeeds).
``reset_to_state`` replays start from states of gym-pusht's own expert runs and replay the next 50 actions.
Per step: the simulated state, coverage, reward, termination/success, n_contacts, keypoints, the 96 x 96 pixels;
``render()`` frames (680 x 680 with the action marker) at a few steps.

    python scripts/interop_pusht.py --gym-pusht-python .cache/interop/gym_pusht/bin/python \\
        [--seeds 50] [--steps 300] [--table docs/pusht_parity.md] [--fixture tests/jepa_envs/tasks/data/...]

Prints the parity table and the speed table, writes interop_out/pusht.json (with its wall time and the run id
scripts/interop.sh gives, ``INTEROP_RUN_ID``), optionally the markdown table and a
small reference file of gym-pusht's own outputs for the unit tests. Exit 1 when a check fails.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PEER = ROOT / "scripts" / "interop_pusht_peer.py"
LEROBOT_PEER = ROOT / "scripts" / "interop_pusht_lerobot_peer.py"
TOL = 1e-6
BATCH = 10                      # episodes per peer process (each holds its frames in memory)
REPLAY_STARTS = (0, 50, 100, 150)
REPLAY_STEPS = 50
RENDER_STEPS = (1, 100, 300)    # render() frames compared, for the first RENDER_EPISODES episodes of a batch
RENDER_EPISODES = 2


def run_peer(python: str, kind: str, inputs: dict, work: Path) -> tuple[dict, dict]:
    src, out = work / f"in-{kind}.npz", work / f"out-{kind}.npz"
    np.savez(src, **inputs)
    done = subprocess.run([python, str(PEER), kind, str(src), str(out)], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{kind} replay in {python} failed:\n{done.stderr[-3000:]}")
    with np.load(out) as data:
        return {k: data[k] for k in data.files}, json.loads(done.stdout.strip().splitlines()[-1])


def random_actions(seeds, steps: int) -> np.ndarray:
    return np.stack([np.random.default_rng(int(s)).uniform(0, 512, (steps, 2)).astype(np.float32) for s in seeds])


def expert_actions(seeds, steps: int, workers: int) -> tuple[np.ndarray, list[int]]:
    """The expert's targets on our env for each seed (one episode per seed), held once it succeeds."""
    from jepa_envs.tasks.pusht_expert import generate_demos

    episodes, _ = generate_demos(len(seeds), seed=int(seeds[0]), task="PushTStandard", only_successes=False,
                                 max_attempts_factor=1, workers=workers)
    out = np.zeros((len(seeds), steps, 2), np.float32)
    lengths = []
    for i, ep in enumerate(episodes):
        acts = ep["actions"][:steps]
        out[i, :len(acts)] = acts
        out[i, len(acts):] = acts[-1]
        lengths.append(len(acts))
    return out, lengths


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(255 ** 2 / mse)


def compare(ours: dict, theirs: dict) -> list[dict]:
    """Per-episode agreement of two replays of the same inputs."""
    rows = []
    for i in range(len(theirs["state"])):
        d_state = np.abs(ours["state"][i] - theirs["state"][i]).max(axis=1)
        over = np.flatnonzero(d_state > TOL)
        succ_o, succ_t = ours["is_success"][i], theirs["is_success"][i]
        first = lambda s: int(np.argmax(s)) if s.any() else -1   # noqa: E731
        frames_equal = (ours["pixels"][i] == theirs["pixels"][i]).all(axis=(1, 2, 3))
        rows.append({
            "max_state_diff": float(d_state.max()), "steps_over_tol": int(len(over)),
            "first_over_tol": int(over[0]) if len(over) else None,
            "max_coverage_diff": float(np.abs(ours["coverage"][i] - theirs["coverage"][i]).max()),
            "max_reward_diff": float(np.abs(ours["reward"][i] - theirs["reward"][i]).max()),
            "success_agrees": bool(first(succ_o) == first(succ_t)), "success": bool(succ_t.any()),
            "terminated_agrees": bool((ours["terminated"][i] == theirs["terminated"][i]).all()),
            "n_contacts_agree": bool((ours["n_contacts"][i] == theirs["n_contacts"][i]).all()),
            "max_keypoint_diff": float(np.abs(ours["keypoints"][i] - theirs["keypoints"][i]).max()),
            "max_velocity_diff": float(np.abs(ours["vel_agent"][i] - theirs["vel_agent"][i]).max()),
            "frames": int(len(frames_equal)), "frames_equal": int(frames_equal.sum()),
            "min_psnr": min(psnr(a, b) for a, b in zip(ours["pixels"][i], theirs["pixels"][i])),
        })
    return rows


def summarise(rows: list[dict], renders: list[float]) -> dict:
    n = len(rows)
    return {
        "episodes": n, "steps": rows[0]["frames"] - 1 if rows else 0,
        "max_state_diff": max(r["max_state_diff"] for r in rows),
        "episodes_within_tol": sum(r["steps_over_tol"] == 0 for r in rows),
        "max_coverage_diff": max(r["max_coverage_diff"] for r in rows),
        "max_reward_diff": max(r["max_reward_diff"] for r in rows),
        "success_agreement": sum(r["success_agrees"] for r in rows), "successes": sum(r["success"] for r in rows),
        "terminated_agreement": sum(r["terminated_agrees"] for r in rows),
        "n_contacts_agreement": sum(r["n_contacts_agree"] for r in rows),
        "max_keypoint_diff": max(r["max_keypoint_diff"] for r in rows),
        "frames_equal": sum(r["frames_equal"] for r in rows), "frames": sum(r["frames"] for r in rows),
        "min_psnr": min(r["min_psnr"] for r in rows),
        "render_frames_equal": sum(p == float("inf") for p in renders), "render_frames": len(renders),
        "render_min_psnr": min(renders) if renders else None,
    }


def replay_all(name: str, seeds, actions, gym_py: str, work: Path, resets=None, keep: dict | None = None) -> dict:
    """gym-pusht, ours on pymunk 6 and ours on pymunk 7 replay the same inputs in batches; per-episode rows."""
    rows = {"pymunk7": [], "pymunk6": []}
    renders = {"pymunk7": [], "pymunk6": []}
    versions, theirs_all = {}, []
    for start in range(0, len(seeds), BATCH):
        inputs = {"seeds": seeds[start:start + BATCH], "actions": actions[start:start + BATCH],
                  "render_steps": np.array([t for t in RENDER_STEPS if t <= actions.shape[1]]),
                  "render_episodes": RENDER_EPISODES}
        if resets is not None:
            inputs["reset_states"] = resets[start:start + BATCH]
        theirs, info = run_peer(gym_py, "gym-pusht", inputs, work)
        versions["gym-pusht"] = info["pymunk"]
        for label, python in (("pymunk6", gym_py), ("pymunk7", sys.executable)):
            ours, info = run_peer(python, "ours", inputs, work)
            versions[label] = info["pymunk"]
            rows[label] += compare(ours, theirs)
            renders[label] += [psnr(a, b) for a, b in zip(ours["renders"], theirs["renders"])]
        theirs_all.append({k: theirs[k] for k in ("state", "is_success")})
        if keep is not None and start == 0:
            keep.update(theirs)
        print(f"[pusht] {name}: episodes {start}-{start + len(inputs['seeds']) - 1} compared", flush=True)
    return {"rows": rows, "summary": {k: summarise(rows[k], renders[k]) for k in rows}, "versions": versions,
            "theirs": {k: np.concatenate([t[k] for t in theirs_all]) for k in ("state", "is_success")}}


def bench(gym_py: str, rounds: int, steps: int) -> dict:
    """Steps/s of gym-pusht and of ours (this project's pymunk) in interleaved blocks, same actions, same run."""
    arms = [("gym-pusht", gym_py, "pixels_agent_pos"), ("ours", sys.executable, "pixels_agent_pos"),
            ("gym-pusht", gym_py, "state"), ("ours", sys.executable, "state"), ("ours", sys.executable, "jepa")]
    times: dict[str, list] = {}
    load_before = os.getloadavg()
    for _ in range(rounds):
        for kind, python, obs_type in arms:
            done = subprocess.run([python, str(PEER), "bench", kind, obs_type, str(steps)], capture_output=True,
                                  text=True)
            if done.returncode != 0:
                raise RuntimeError(f"bench {kind} {obs_type} failed:\n{done.stderr[-2000:]}")
            r = json.loads(done.stdout.strip().splitlines()[-1])
            times.setdefault(f"{kind}/{obs_type}", []).append((r["wall_s"], r["cpu_s"]))
    out = {"steps_per_block": steps, "rounds": rounds, "load_before": load_before, "load_after": os.getloadavg()}
    for key, values in times.items():
        wall, cpu = np.median([v[0] for v in values]), np.median([v[1] for v in values])
        out[key] = {"steps_per_s_wall": steps / wall, "steps_per_s_cpu": steps / cpu}
    for obs_type in ("pixels_agent_pos", "state"):
        for clock in ("wall", "cpu"):
            out[f"ratio_{obs_type}_{clock}"] = (out[f"ours/{obs_type}"][f"steps_per_s_{clock}"]
                                                / out[f"gym-pusht/{obs_type}"][f"steps_per_s_{clock}"])
    return out


def write_fixture(path: Path, seeds, random_acts, expert_acts, theirs_random: dict, theirs_expert: dict,
                  episodes: int = 2, steps: int = 30) -> None:
    """gym-pusht's own outputs for a few short episodes, for tests/jepa_envs/tasks/test_pusht_standard.py."""
    out = {}
    for name, acts, theirs in (("random", random_acts, theirs_random), ("expert", expert_acts, theirs_expert)):
        out[f"{name}_seeds"] = seeds[:episodes]
        out[f"{name}_actions"] = acts[:episodes, :steps]
        for key in ("state", "pixels", "coverage", "reward", "terminated", "is_success", "n_contacts", "keypoints",
                    "agent_pos"):
            out[f"{name}_{key}"] = theirs[key][:episodes, :steps + 1]
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **out)


def table_lines(result: dict) -> list[str]:
    def fmt(x):
        return "0" if x == 0 else f"{x:.1e}"

    lines = ["| actions | pymunk | episodes x steps | max abs state diff | episodes within 1e-6 "
             "| max abs coverage diff | success agreement | n_contacts agree | frames pixel-identical | min PSNR "
             "| render() frames identical |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in ("random", "expert", "reset_to_state"):
        for label in ("pymunk7", "pymunk6"):
            s = result[name]["summary"][label]
            version = result[name]["versions"][label]
            lines.append(
                f"| {name} | {version} ({'ours' if label == 'pymunk7' else 'gym-pusht venv'}) | {s['episodes']} x "
                f"{s['steps']} | {fmt(s['max_state_diff'])} | {s['episodes_within_tol']}/{s['episodes']} | "
                f"{fmt(s['max_coverage_diff'])} | {s['success_agreement']}/{s['episodes']} ({s['successes']} "
                f"successes) | {s['n_contacts_agreement']}/{s['episodes']} | {s['frames_equal']}/{s['frames']} | "
                f"{'inf' if s['min_psnr'] == float('inf') else round(s['min_psnr'], 1)} dB | "
                f"{s['render_frames_equal']}/{s['render_frames']} |")
    return lines


def speed_lines(speed: dict) -> list[str]:
    lines = ["| observation | gym-pusht steps/s (CPU / wall) | ours steps/s (CPU / wall) | ratio ours / gym-pusht "
             "(CPU / wall) |", "|---|---|---|---|"]
    for obs_type in ("pixels_agent_pos", "state"):
        g, o = speed[f"gym-pusht/{obs_type}"], speed[f"ours/{obs_type}"]
        lines.append(f"| {obs_type} | {g['steps_per_s_cpu']:.0f} / {g['steps_per_s_wall']:.0f} | "
                     f"{o['steps_per_s_cpu']:.0f} / {o['steps_per_s_wall']:.0f} | "
                     f"{speed[f'ratio_{obs_type}_cpu']:.2f}x / {speed[f'ratio_{obs_type}_wall']:.2f}x |")
    o = speed["ours/jepa"]
    lines.append(f"| jepa (top_image + agent_pos) | - | {o['steps_per_s_cpu']:.0f} / {o['steps_per_s_wall']:.0f} | - |")
    return lines


def _run(cmd: list[str], what: str, env: dict | None = None) -> subprocess.CompletedProcess:
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        raise RuntimeError(f"{what} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    return done


def _lerobot_write(lerobot_py: str, episodes: list[dict], root: Path, work: Path, size: int = 96,
                   action_scale: float = 1.0) -> None:
    """LeRobot's own writer makes a lerobot/pusht-layout dataset of ``episodes`` (frames resized to ``size``,
    actions multiplied by ``action_scale``: the mismatches the importer must name)."""
    from PIL import Image

    frames = np.concatenate([e["obs"]["top_image"] for e in episodes])
    if size != frames.shape[1]:
        frames = np.stack([np.asarray(Image.fromarray(f).resize((size, size), Image.BILINEAR)) for f in frames])
    src = work / f"lerobot-in-{size}-{action_scale}.npz"
    np.savez(src, frames=frames, state=np.concatenate([e["obs"]["agent_pos"] for e in episodes]).astype(np.float32),
             action=(np.concatenate([e["actions"] for e in episodes]) * action_scale).astype(np.float32),
             episode_ends=np.cumsum([len(e["actions"]) for e in episodes]),
             task="Push the T-shaped block onto the T-shaped target.")
    _run([lerobot_py, str(LEROBOT_PEER), "write", str(src), str(root)], "LeRobot write (lerobot/pusht layout)")


def check_lerobot_layout(lerobot_py: str, work: Path) -> dict:
    """lerobot/pusht's layout written by LeRobot 0.4.4 itself: imported as PushTStandard and trained from with
    `jepa-policy train --dataset ROOT` as it is; a dataset of the wrong image size or action units refused in one
    line; our export of PushTStandard demos read by LeRobot's reader."""
    import h5py

    from jepa_envs.datasets.hdf5 import demo_names, write_dataset
    from jepa_envs.tasks.pusht_expert import generate_demos

    episodes, env_args = generate_demos(3, seed=200, task="PushTStandard")
    env = {**os.environ, "JEPA_DATA_CACHE": str(work / "cache")}
    result = {}
    root = work / "lerobot-pusht"
    _lerobot_write(lerobot_py, episodes, root, work)
    info = json.loads((root / "meta" / "info.json").read_text())
    result["layout"] = {k: info["features"][k]["shape"] for k in ("observation.image", "observation.state", "action")}
    result["layout"]["fps"] = info["fps"]
    imported = work / "imported.hdf5"
    _run([sys.executable, "-m", "jepa_envs.cli", "lerobot", "import", str(root), str(imported), "--task",
          "PushTStandard"], "jepa-envs lerobot import", env)
    with h5py.File(imported) as f:
        names = demo_names(f["data"])
        got = {key: np.concatenate([f["data"][n][key][()] for n in names]) for key in ("actions", "obs/agent_pos",
                                                                                         "obs/top_image")}
    frames = np.concatenate([e["obs"]["top_image"] for e in episodes])
    result["actions_equal"] = bool(np.array_equal(got["actions"], np.concatenate([e["actions"] for e in episodes])))
    result["state_equal"] = bool(np.array_equal(got["obs/agent_pos"],
                                                np.concatenate([e["obs"]["agent_pos"] for e in episodes])))
    result["frames_psnr_db"] = round(psnr(got["obs/top_image"], frames), 1)
    done = _run([sys.executable, "-m", "jepa_policy.cli", "train", "--task", "PushTStandard", "--preset", "quick",
                 "--dataset", str(root), "--steps", "2", "--warmup-steps", "1", "--eval-every", "0", "--out",
                 str(work / "train"), "--no-progress"], "jepa-policy train --dataset ROOT", env)
    result["train_from_root"] = json.loads(done.stdout.strip().splitlines()[-1])["step"] == 2
    refusals = {}
    for name, kwargs in (("84 x 84 frames", {"size": 84}), ("actions in [0, 1]", {"action_scale": 1 / 512})):
        bad = work / f"lerobot-bad-{len(refusals)}"
        _lerobot_write(lerobot_py, episodes, bad, work, **kwargs)
        out = subprocess.run([sys.executable, "-m", "jepa_policy.cli", "train", "--task", "PushTStandard", "--preset",
                              "quick", "--dataset", str(bad), "--steps", "2", "--out", str(work / "bad"),
                              "--no-progress"], capture_output=True, text=True, env=env)
        lines = out.stderr.strip().splitlines()
        refusals[name] = {"exit": out.returncode, "lines": len(lines), "message": lines[-1] if lines else ""}
    out = subprocess.run([sys.executable, "-m", "jepa_policy.cli", "train", "--task", "PushT", "--preset", "quick",
                          "--dataset", str(root), "--steps", "2", "--out", str(work / "bad"), "--no-progress"],
                         capture_output=True, text=True, env=env)
    lines = out.stderr.strip().splitlines()
    refusals["lerobot/pusht as --task PushT"] = {"exit": out.returncode, "lines": len(lines),
                                                 "message": lines[-1] if lines else ""}
    result["refusals"] = refusals
    # ours -> LeRobot's reader: our export of PushTStandard demos is in the same layout
    demos = work / "standard.hdf5"
    write_dataset(demos, episodes, env_args)
    export = work / "export"
    _run([sys.executable, "-m", "jepa_envs.cli", "lerobot", "export", str(demos), str(export)],
         "jepa-envs lerobot export")
    _run([lerobot_py, str(LEROBOT_PEER), "read", str(export), str(work / "read.npz")], "LeRobot read")
    with np.load(work / "read.npz") as back:
        result["export_read_by_lerobot"] = {
            "features": sorted(json.loads((export / "meta" / "info.json").read_text())["features"]),
            "frames_equal": bool(np.array_equal(back["observation.image"], frames)),
            "actions_equal": bool(np.array_equal(back["action"], got["actions"].astype(np.float32)))}
    result["ok"] = bool(result["actions_equal"] and result["state_equal"] and result["train_from_root"]
                        and all(r["exit"] != 0 and r["lines"] == 1 for r in refusals.values())
                        and result["export_read_by_lerobot"]["frames_equal"]
                        and result["export_read_by_lerobot"]["actions_equal"])
    return result


def print_lerobot_layout(result: dict) -> None:
    print(f"lerobot/pusht layout written by LeRobot 0.4.4 ({result['layout']}): imported as PushTStandard, actions "
          f"{'equal' if result['actions_equal'] else 'DIFFER'}, "
          f"state {'equal' if result['state_equal'] else 'DIFFER'}, "
          f"frames PSNR {result['frames_psnr_db']} dB (LeRobot's AV1); jepa-policy train --dataset ROOT "
          f"{'trains' if result['train_from_root'] else 'FAILED'}")
    for name, r in result["refusals"].items():
        print(f"  refused ({name}): exit {r['exit']}, {r['lines']} line: {r['message']}")
    e = result["export_read_by_lerobot"]
    print(f"our PushTStandard export read by LeRobotDataset: features {e['features']}, frames "
          f"{'equal' if e['frames_equal'] else 'DIFFER'}, actions {'equal' if e['actions_equal'] else 'DIFFER'}")


def check_pusht(gym_py: str, seeds: int, steps: int, workers: int, bench_rounds: int, bench_steps: int,
                fixture: Path | None = None) -> dict:
    seed_list = np.arange(seeds)
    result = {"seeds": seeds, "steps": steps}
    with tempfile.TemporaryDirectory(prefix="jepa-pusht-interop-") as tmp:
        work = Path(tmp)
        rand = random_actions(seed_list, steps)
        keep_random, keep_expert = {}, {}
        result["random"] = replay_all("random actions", seed_list, rand, gym_py, work, keep=keep_random)
        expert, lengths = expert_actions(seed_list, steps, workers)
        result["expert_lengths"] = lengths
        result["expert"] = replay_all("expert actions", seed_list, expert, gym_py, work, keep=keep_expert)
        # reset_to_state: states gym-pusht itself reached on the expert runs, then the actions that followed
        theirs = result["expert"]["theirs"]["state"]
        starts = [(i, t) for i in range(seeds) for t in REPLAY_STARTS if t + REPLAY_STEPS <= steps]
        resets = np.array([theirs[i, t] for i, t in starts])
        acts = np.stack([expert[i, t:t + REPLAY_STEPS] for i, t in starts])
        result["reset_to_state"] = replay_all("reset_to_state replays", np.array([i for i, _ in starts]), acts,
                                              gym_py, work, resets=resets)
        if fixture is not None:
            write_fixture(fixture, seed_list, rand, expert, keep_random, keep_expert)
    for name in ("random", "expert", "reset_to_state"):
        del result[name]["theirs"]
    result["speed"] = bench(gym_py, bench_rounds, bench_steps)
    ok = all(s["episodes_within_tol"] == s["episodes"] and s["success_agreement"] == s["episodes"]
             and s["max_coverage_diff"] <= TOL for name in ("random", "expert", "reset_to_state")
             for s in result[name]["summary"].values())
    result["ok"] = bool(ok and result["speed"]["ratio_pixels_agent_pos_cpu"] >= 1.0)
    return result


def print_pusht(result: dict) -> None:
    print(f"gym-pusht 0.1.8 (its own code, pymunk {result['random']['versions']['gym-pusht']}) beside our standard "
          f"PushT, {result['seeds']} seeds x {result['steps']} steps")
    print("\n".join(table_lines(result)))
    speed = result["speed"]
    print(f"step speed, {speed['rounds']} interleaved rounds of {speed['steps_per_block']} steps, medians; load "
          f"{' '.join(f'{x:.1f}' for x in speed['load_before'])} before, "
          f"{' '.join(f'{x:.1f}' for x in speed['load_after'])} after")
    print("\n".join(speed_lines(speed)))


def check_sizes(gym_py: str) -> list[dict]:
    """gym-pusht's other frame sizes (visualization_width/height, observation_width/height) in both envs."""
    done = _run([gym_py, str(PEER), "sizes"], "frame sizes")
    return json.loads(done.stdout.strip().splitlines()[-1])


def sizes_lines(rows: list[dict]) -> list[str]:
    lines = ["| visualization_width x height | observation_width x height | render() frames identical | "
             "pixels identical |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['visualization'][0]} x {r['visualization'][1]} | {r['observation'][0]} x "
                     f"{r['observation'][1]} | {r['render_equal']}/{r['frames']} | {r['pixels_equal']}/{r['frames']} |")
    return lines


def write_table(path: Path, result: dict, argv: list[str]) -> None:
    speed = result["speed"]
    lengths = result["expert_lengths"]
    text = [
        "# Parity of the standard PushT with gym-pusht 0.1.8",
        "",
        f"Written by `make interop` (scripts/interop_pusht.py, {' '.join(argv)}) on "
        f"{datetime.date.today().isoformat()}; do not edit by hand. gym-pusht 0.1.8 ran in its own venv "
        f"(pymunk {result['random']['versions']['gym-pusht']}); ours ran with this project's pymunk "
        f"({result['random']['versions']['pymunk7']}) and, as a control, with pymunk "
        f"{result['random']['versions']['pymunk6']} inside gym-pusht's venv. Each episode: the same seed, then the "
        f"same actions in both (random: uniform targets over the table; expert: our scripted expert's targets, "
        f"planned on our env, {np.mean(lengths):.0f} steps on average before it succeeded, then held); "
        f"reset_to_state: {REPLAY_STEPS}-step replays from states of gym-pusht's own expert runs at steps "
        f"{', '.join(map(str, REPLAY_STARTS))}. State = agent x, y, block x, y, block angle as simulated.",
        "",
        *table_lines(result),
        "",
        f"Step speed in the same run ({speed['rounds']} interleaved rounds of {speed['steps_per_block']} random-action "
        f"steps per arm, medians; load average {' '.join(f'{x:.1f}' for x in speed['load_before'])} before, "
        f"{' '.join(f'{x:.1f}' for x in speed['load_after'])} after, on {os.cpu_count()} shared cores):",
        "",
        *speed_lines(speed),
        "",
    ]
    if result.get("sizes"):
        text += ["Other frame sizes (gym-pusht's `visualization_width/height` for `render()`, "
                 "`observation_width/height` for `pixels`), seed 3, reset and 5 actions, both envs in gym-pusht's "
                 "venv:", "",
                 *sizes_lines(result["sizes"]), ""]
    path.write_text("\n".join(text))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gym-pusht-python", required=True, help="python of the gym-pusht venv")
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes planning expert episodes")
    parser.add_argument("--bench-rounds", type=int, default=3)
    parser.add_argument("--bench-steps", type=int, default=1000)
    parser.add_argument("--table", type=Path, help="write the parity table (markdown) here")
    parser.add_argument("--fixture", type=Path, help="write gym-pusht's outputs for the unit tests here")
    parser.add_argument("--lerobot-python", help="python of the LeRobot venv: also check lerobot/pusht's layout "
                        "written by LeRobot itself (import, train --dataset ROOT, refusals, export read back)")
    parser.add_argument("--skip-parity", action="store_true", help="only the lerobot/pusht layout check")
    parser.add_argument("--out", default="interop_out")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(exist_ok=True)
    ok = True
    if not args.skip_parity:
        started = time.perf_counter()
        result = check_pusht(args.gym_pusht_python, args.seeds, args.steps, args.workers, args.bench_rounds,
                             args.bench_steps, args.fixture)
        result["sizes"] = check_sizes(args.gym_pusht_python)
        result["ok"] = result["ok"] and all(r["render_equal"] == r["pixels_equal"] == r["frames"]
                                            for r in result["sizes"])
        print_pusht(result)
        print("\n".join(sizes_lines(result["sizes"])))
        result["seconds"] = round(time.perf_counter() - started, 1)
        result["run_id"] = os.environ.get("INTEROP_RUN_ID")   # scripts/interop.sh's, for its summary
        (out / "pusht.json").write_text(json.dumps(result, indent=2, default=str))
        if args.table:
            write_table(args.table, result, [f"--seeds {args.seeds} --steps {args.steps}"])
        print(f"gym-pusht parity: {'passed' if result['ok'] else 'FAILED'} (details in {out / 'pusht.json'})")
        ok = result["ok"]
    if args.lerobot_python:
        with tempfile.TemporaryDirectory(prefix="jepa-pusht-lerobot-") as tmp:
            layout = check_lerobot_layout(args.lerobot_python, Path(tmp))
        print_lerobot_layout(layout)
        (out / "pusht_lerobot.json").write_text(json.dumps(layout, indent=2, default=str))
        print(f"lerobot/pusht layout: {'passed' if layout['ok'] else 'FAILED'}")
        ok = ok and layout["ok"]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
