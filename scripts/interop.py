"""`make interop` (scripts/interop.sh builds the venvs): our integrations checked by code no one here wrote.

LeRobot (its own dataset code, LeRobot 0.4.4, in its venv):
  1. PushT demos exported by `jepa-envs lerobot export` (lossless and AV1) are loaded with LeRobot's
     ``LeRobotDataset``: every frame, state, action, index and task string compared with ours.
  2. A dataset written by LeRobot's ``LeRobotDataset.create / add_frame / save_episode / finalize`` is imported
     with `jepa-envs lerobot import` and compared with what was added; `jepa-policy train --dataset ROOT`
     trains from it.
  3. lerobot/pusht's layout written by LeRobot itself (``check_lerobot_layout`` in scripts/interop_pusht.py).
openpi (the published ``openpi-client``, in its venv): see ``check_openpi``.

Prints one table per check and writes interop_out/<part>.json (lerobot.json, openpi.json) with its wall time and the
run id scripts/interop.sh gives (``INTEROP_RUN_ID``). Exit 1 when any check fails.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PEER = ROOT / "scripts" / "interop_lerobot_peer.py"


def run(cmd: list[str], what: str) -> str:
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"{what} failed ({out.returncode}):\n{out.stderr[-3000:]}")
    return out.stdout.strip().splitlines()[-1]


def demo_arrays(path: Path) -> dict:
    from jepa_envs.datasets.hdf5 import demo_names

    with h5py.File(path) as f:
        names = demo_names(f["data"])
        get = lambda key: np.concatenate([f["data"][n][key][()] for n in names])   # noqa: E731
        lengths = [int(f["data"][n]["actions"].shape[0]) for n in names]
        return {"frames": get("obs/top_image"), "state": get("obs/agent_pos"), "action": get("actions"),
                "episode_ends": np.cumsum(lengths), "lengths": lengths,
                "tasks": [f["data"][n].attrs.get("task", "") for n in names]}


def frame_error(a: np.ndarray, b: np.ndarray) -> dict:
    diff = np.abs(a.astype(np.float64) - b.astype(np.float64))
    mse = float((diff ** 2).mean())
    return {"max": float(diff.max()), "mean": round(float(diff.mean()), 3),
            "p99": float(np.percentile(diff, 99)),
            "psnr_db": None if mse == 0 else round(10 * np.log10(255 ** 2 / mse), 1)}


def check_lerobot(py: str, work: Path) -> dict:
    from jepa_envs.datasets.hdf5 import write_dataset
    from jepa_envs.tasks.pusht_expert import generate_demos

    demos = work / "pusht.hdf5"
    episodes, env_args = generate_demos(6, seed=100)
    write_dataset(demos, episodes, env_args)
    ours = demo_arrays(demos)
    result = {"read_by_lerobot": {}, "written_by_lerobot": {}}
    # 1. ours -> LeRobot's reader
    for codec in ("lossless", "av1"):
        out = work / f"export-{codec}"
        run([sys.executable, "-m", "jepa_envs.cli", "lerobot", "export", str(demos), str(out), "--codec", codec],
            f"jepa-envs lerobot export --codec {codec}")
        info = json.loads(run([py, str(PEER), "read", str(out), str(work / f"read-{codec}.npz")], "LeRobot read"))
        got = np.load(work / f"read-{codec}.npz")
        starts = np.concatenate([[0], ours["episode_ends"][:-1]])
        expected_episode = np.repeat(np.arange(len(ours["lengths"])), ours["lengths"])
        expected_frame = np.concatenate([np.arange(n) for n in ours["lengths"]])
        row = {
            "lerobot": info, "frames": frame_error(got["observation.images.top"], ours["frames"]),
            "frames_equal": bool(np.array_equal(got["observation.images.top"], ours["frames"])),
            "actions_equal": bool(np.array_equal(got["action"], ours["action"])),
            "state_equal": bool(np.array_equal(got["observation.state"], ours["state"])),
            "episode_index_equal": bool(np.array_equal(got["episode_index"].reshape(-1), expected_episode)),
            "frame_index_equal": bool(np.array_equal(got["frame_index"].reshape(-1), expected_frame)),
            "timestamps_equal": bool(np.allclose(got["timestamp"].reshape(-1), expected_frame / 10.0, atol=1e-6)),
            "tasks": sorted(set(got["tasks"].tolist())), "episode_starts": starts.tolist()[:3]}
        row["ok"] = all(row[k] for k in ("actions_equal", "state_equal", "episode_index_equal", "frame_index_equal",
                                         "timestamps_equal")) and (codec != "lossless" or row["frames_equal"])
        result["read_by_lerobot"][codec] = row
    # 2. LeRobot's writer -> ours
    np.savez(work / "to-lerobot.npz", frames=ours["frames"], state=ours["state"], action=ours["action"],
             episode_ends=ours["episode_ends"], fps=10,
             tasks=np.array([f"push the T onto the target, take {i}" for i in range(len(ours["lengths"]))]))
    written = work / "written-by-lerobot"
    info = json.loads(run([py, str(PEER), "write", str(work / "to-lerobot.npz"), str(written)], "LeRobot write"))
    back = work / "imported.hdf5"
    run([sys.executable, "-m", "jepa_envs.cli", "lerobot", "import", str(written), str(back), "--task", "PushT"],
        "jepa-envs lerobot import")
    got = demo_arrays(back)
    row = {"lerobot": info, "frames": frame_error(got["frames"], ours["frames"]),
           "actions_equal": bool(np.array_equal(got["action"], ours["action"])),
           "state_equal": bool(np.array_equal(got["state"], ours["state"])),
           "episode_boundaries_equal": bool(np.array_equal(got["episode_ends"], ours["episode_ends"])),
           "tasks_equal": [str(t) for t in got["tasks"]] == [f"push the T onto the target, take {i}"
                                                             for i in range(len(ours["lengths"]))]}
    train = run([sys.executable, "-m", "jepa_policy.cli", "train", "--task", "PushT", "--preset", "quick",
                 "--dataset", str(written), "--steps", "2", "--warmup-steps", "1", "--eval-every", "0",
                 "--out", str(work / "train-from-lerobot"), "--no-progress"], "jepa-policy train --dataset ROOT")
    row["train_from_root"] = json.loads(train)["step"] == 2
    row["ok"] = all(row[k] for k in ("actions_equal", "state_equal", "episode_boundaries_equal", "tasks_equal",
                                     "train_from_root")) and row["frames"]["psnr_db"] is not None
    result["written_by_lerobot"] = row
    result["ok"] = all(r["ok"] for r in result["read_by_lerobot"].values()) and row["ok"]
    return result


def print_lerobot(result: dict) -> None:
    print("LeRobot 0.4.4 (its own LeRobotDataset code) with our files")
    print(f"{'direction':<44}{'actions':>8}{'state':>7}{'indices':>8}  frames (0-255)")
    for codec, row in result["read_by_lerobot"].items():
        indices = row["episode_index_equal"] and row["frame_index_equal"] and row["timestamps_equal"]
        print(f"{'ours -> LeRobotDataset, ' + codec:<44}{_eq(row['actions_equal']):>8}{_eq(row['state_equal']):>7}"
              f"{_eq(indices):>8}  max {row['frames']['max']:.0f}, mean {row['frames']['mean']}, "
              f"PSNR {row['frames']['psnr_db'] or 'inf'} dB ({row['lerobot']['video_backend']})")
    row = result["written_by_lerobot"]
    print(f"{'LeRobotDataset.create (' + row['lerobot']['vcodec'] + ') -> ours':<44}{_eq(row['actions_equal']):>8}"
          f"{_eq(row['state_equal']):>7}{_eq(row['episode_boundaries_equal']):>8}  max {row['frames']['max']:.0f}, "
          f"mean {row['frames']['mean']}, PSNR {row['frames']['psnr_db']} dB; tasks {_eq(row['tasks_equal'])}, "
          f"train --dataset ROOT {_eq(row['train_from_root'])}")


def _eq(ok: bool) -> str:
    return "equal" if ok else "DIFFER"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lerobot-python", required=True)
    parser.add_argument("--openpi-python", required=True)
    parser.add_argument("--out", default="interop_out")
    parser.add_argument("--only", choices=("lerobot", "openpi"))
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(exist_ok=True)
    report = {}
    work = Path(tempfile.mkdtemp(prefix="jepa-interop-"))
    try:
        if args.only in (None, "lerobot"):
            from interop_pusht import check_lerobot_layout, print_lerobot_layout
            started = time.perf_counter()
            report["lerobot"] = check_lerobot(args.lerobot_python, work)
            print_lerobot(report["lerobot"])
            (work / "layout").mkdir()
            layout = report["lerobot"]["lerobot_pusht_layout"] = check_lerobot_layout(args.lerobot_python,
                                                                                      work / "layout")
            print_lerobot_layout(layout)
            report["lerobot"]["ok"] = report["lerobot"]["ok"] and layout["ok"]
            report["lerobot"]["seconds"] = round(time.perf_counter() - started, 1)
        if args.only in (None, "openpi"):
            from interop_openpi import check_openpi, print_openpi
            started = time.perf_counter()
            report["openpi"] = check_openpi(args.openpi_python, work)
            report["openpi"]["seconds"] = round(time.perf_counter() - started, 1)
            print_openpi(report["openpi"])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    for part, result in report.items():
        result["run_id"] = os.environ.get("INTEROP_RUN_ID")
        (out / f"{part}.json").write_text(json.dumps(result, indent=2, default=str))
    ok = all(part["ok"] for part in report.values())
    print(f"interop: {'all checks passed' if ok else 'FAILED'} (details in "
          f"{', '.join(str(out / f'{part}.json') for part in report)})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
