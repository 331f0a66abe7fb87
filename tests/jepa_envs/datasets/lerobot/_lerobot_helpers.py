"""Reading back what the LeRobot tests wrote, and editing copies of an export into bad datasets."""
from __future__ import annotations

import json
import shutil

import h5py
import pytest

from jepa_envs.datasets.hdf5 import demo_names
from jepa_envs.datasets.lerobot import LeRobotError, import_lerobot


def arrays(path) -> list[dict]:
    """Every episode's arrays (and task string) of a robomimic-layout HDF5 file."""
    with h5py.File(path) as f:
        return [{key: f["data"][n][key][()] for key in ("actions", "states", "rewards", "dones")}
                | {f"obs/{k}": f["data"][n]["obs"][k][()] for k in f["data"][n]["obs"]}
                | {"task": f["data"][n].attrs.get("task")} for n in demo_names(f["data"])]


def copy(root, tmp_path):
    dst = tmp_path / "ds"
    shutil.copytree(root, dst)
    return dst


def edit_info(root, **changes):
    info = json.loads((root / "meta/info.json").read_text())
    info.update(changes)
    (root / "meta/info.json").write_text(json.dumps(info))


def refused(root, tmp_path, match, task="PushT", **kwargs):
    """Importing ``root`` raises one line matching ``match`` and leaves nothing behind."""
    out = tmp_path / "out.hdf5"
    with pytest.raises(LeRobotError, match=match) as err:
        import_lerobot(root, out, task, **kwargs)
    assert "\n" not in str(err.value)
    assert not out.exists() and not list(tmp_path.glob("out.hdf5.*")), "nothing half-written"
    return str(err.value)
