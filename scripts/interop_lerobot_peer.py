"""Runs inside the LeRobot venv (scripts/interop.sh): LeRobot's own dataset code reads or writes a dataset.

    python interop_lerobot_peer.py read ROOT OUT.npz      # LeRobotDataset(root=ROOT): every frame, as LeRobot serves it
    python interop_lerobot_peer.py write IN.npz ROOT      # LeRobotDataset.create / add_frame / save_episode / finalize

Nothing of this project is imported here: only lerobot, numpy and torch.
"""
import json
import sys

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset


def read(root: str, out: str) -> None:
    ds = LeRobotDataset("local/jepa-export", root=root)
    cams = ds.meta.camera_keys
    arrays = {k: [] for k in [*cams, "observation.state", "action", "episode_index", "frame_index", "timestamp"]}
    tasks = []
    for i in range(len(ds)):
        item = ds[i]
        for cam in cams:   # LeRobot serves float32 CHW in [0, 1]: back to the uint8 HWC it decoded
            arrays[cam].append(np.round(item[cam].numpy().transpose(1, 2, 0) * 255).astype(np.uint8))
        for key in ("observation.state", "action", "episode_index", "frame_index", "timestamp"):
            arrays[key].append(item[key].numpy())
        tasks.append(item["task"])
    np.savez(out, tasks=np.array(tasks), cameras=np.array(cams), fps=ds.fps,
             **{k: np.stack(v) for k, v in arrays.items()})
    print(json.dumps({"frames": len(ds), "episodes": ds.num_episodes, "cameras": cams, "fps": ds.fps,
                      "codebase_version": ds.meta.info["codebase_version"],
                      "video_backend": ds.video_backend}))


def write(src: str, root: str) -> None:
    data = np.load(src)
    frames, state, action, ends = data["frames"], data["state"], data["action"], data["episode_ends"]
    features = {
        "observation.images.top": {"dtype": "video", "shape": tuple(frames.shape[1:]),
                                   "names": ["height", "width", "channels"]},
        "observation.state": {"dtype": "float32", "shape": (state.shape[1],), "names": ["x", "y"]},
        "action": {"dtype": "float32", "shape": (action.shape[1],), "names": ["x", "y"]},
    }
    ds = LeRobotDataset.create("local/lerobot-written", fps=int(data["fps"]), features=features, root=root,
                               robot_type="pusht-sim")
    start = 0
    for e, end in enumerate(ends):
        for t in range(start, end):
            ds.add_frame({"observation.images.top": frames[t], "observation.state": state[t],
                          "action": action[t], "task": str(data["tasks"][e])})
        ds.save_episode()
        start = end
    ds.finalize()
    print(json.dumps({"frames": int(ends[-1]), "episodes": len(ends), "vcodec": ds.vcodec}))


if __name__ == "__main__":
    {"read": read, "write": write}[sys.argv[1]](*sys.argv[2:])
