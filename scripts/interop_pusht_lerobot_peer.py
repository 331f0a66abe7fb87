"""Runs inside the LeRobot venv (scripts/interop.sh): LeRobot's own code writes demonstrations in the layout of
LeRobot's ``lerobot/pusht`` (the standard Push-T's dataset) or reads one back.

    python interop_pusht_lerobot_peer.py write IN.npz ROOT     # LeRobotDataset.create / add_frame / save_episode
    python interop_pusht_lerobot_peer.py read ROOT OUT.npz     # LeRobotDataset(root=ROOT): every frame

The layout is lerobot/pusht's: ``observation.image`` (video, 96 x 96 x 3), ``observation.state`` (float32 [2], the
agent position, names {"motors": [motor_0, motor_1]}), ``action`` (float32 [2], the absolute target, same
names), 10 fps. lerobot/pusht also has ``next.reward``, ``next.done`` and ``next.success`` (shape [1]); LeRobot 0.4.4
cannot write a shape-[1] feature beside numpy 2.4 (its ``datasets`` encoder calls ``float()`` on a 1-element array,
which numpy 2.4 refuses), so they are left out. IN.npz: frames, state, action, episode_ends, task. Nothing of this
project is imported here: only lerobot, numpy and torch.
"""
import json
import sys

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

MOTORS = {"motors": ["motor_0", "motor_1"]}


def write(src: str, root: str) -> None:
    data = np.load(src)
    frames, ends = data["frames"], data["episode_ends"]
    features = {
        "observation.image": {"dtype": "video", "shape": tuple(frames.shape[1:]),
                              "names": ["height", "width", "channel"]},
        "observation.state": {"dtype": "float32", "shape": (2,), "names": MOTORS},
        "action": {"dtype": "float32", "shape": (2,), "names": MOTORS},
    }
    ds = LeRobotDataset.create("local/pusht-layout", fps=10, features=features, root=root, robot_type="unknown")
    start = 0
    for end in ends:
        for t in range(start, end):
            ds.add_frame({"observation.image": frames[t], "observation.state": data["state"][t],
                          "action": data["action"][t], "task": str(data["task"])})
        ds.save_episode()
        start = end
    ds.finalize()
    print(json.dumps({"frames": int(ends[-1]), "episodes": len(ends), "vcodec": ds.vcodec,
                      "features": sorted(ds.meta.features)}))


def read(root: str, out: str) -> None:
    ds = LeRobotDataset("local/pusht-layout", root=root)
    keys = ["observation.state", "action", "episode_index", "frame_index"]
    arrays = {k: [] for k in ["observation.image", *keys]}
    for i in range(len(ds)):
        item = ds[i]
        arrays["observation.image"].append(np.round(item["observation.image"].numpy().transpose(1, 2, 0) * 255)
                                           .astype(np.uint8))
        for key in keys:
            arrays[key].append(item[key].numpy())
    np.savez(out, **{k: np.stack(v) for k, v in arrays.items()})
    print(json.dumps({"frames": len(ds), "episodes": ds.num_episodes, "fps": ds.fps}))


if __name__ == "__main__":
    {"write": write, "read": read}[sys.argv[1]](*sys.argv[2:])
