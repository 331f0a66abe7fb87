"""LeRobot's lerobot/pusht layout (one ``observation.image`` 96 x 96, ``observation.state`` = agent position,
``action`` = absolute target, 10 fps) for the standard PushT: written by our exporter, imported and trained from as
it is; a dataset of the wrong image size, of normalised actions, or of the standard T given to the embedded PushT
refused in one line naming the mismatch. (`make interop` checks the same layout written by LeRobot's own code.)"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from _lerobot_helpers import arrays, refused

from jepa_envs.datasets.hdf5 import write_dataset
from jepa_envs.datasets.lerobot import export_lerobot, import_lerobot, recorded_task
from jepa_envs.tasks.pusht_expert import generate_demos


@pytest.fixture(scope="module")
def standard_demos():
    return generate_demos(2, seed=200, task="PushTStandard")


def _export(demos, tmp_path, name, image_size=None, action_scale=1.0):
    episodes, env_args = demos
    if image_size is not None:
        episodes, env_args = generate_demos(2, seed=200, task="PushTStandard", image_size=image_size)
    episodes = [{**e, "actions": (e["actions"] * action_scale).astype(e["actions"].dtype)} for e in episodes]
    src = tmp_path / f"{name}.hdf5"
    write_dataset(src, episodes, env_args)
    root = tmp_path / name
    export_lerobot(src, root)
    return src, root


def test_standard_demos_export_in_lerobot_pusht_layout_and_import_back(standard_demos, tmp_path):
    src, root = _export(standard_demos, tmp_path, "std")
    info = json.loads((root / "meta/info.json").read_text())
    assert info["fps"] == 10
    assert info["features"]["observation.image"]["shape"] == [96, 96, 3]
    assert info["features"]["observation.state"]["shape"] == [2]
    assert info["features"]["action"]["shape"] == [2]
    assert not any(k.startswith("observation.images.") for k in info["features"])
    back = tmp_path / "back.hdf5"
    assert import_lerobot(root, back)["task"] == "PushTStandard"   # found from the dataset, no --task
    for ours, theirs in zip(arrays(src), arrays(back)):
        for key in ("actions", "obs/agent_pos", "obs/top_image"):
            assert np.array_equal(ours[key], theirs[key]), key
    # lerobot/pusht's task string, not the gym id's pieces ("gym pusht/PushT-v0")
    assert {a["task"] for a in arrays(back)} == {"Push the T-shaped block onto the T-shaped target."}


def test_train_dataset_root_trains_on_the_layout_as_it_is(standard_demos, tmp_path, monkeypatch, capsys):
    """Without --task: the export records its task (robot_type jepa/PushTStandard); training took the default
    PushT and refused the dataset until it was named."""
    from jepa_policy.cli import main

    monkeypatch.setenv("JEPA_DATA_CACHE", str(tmp_path / "cache"))
    _, root = _export(standard_demos, tmp_path, "std")
    assert main(["train", "--preset", "quick", "--dataset", str(root), "--steps", "2",
                 "--warmup-steps", "1", "--eval-every", "0", "--out", str(tmp_path / "run"),
                 "--no-progress"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out.strip().splitlines()[-1])["step"] == 2
    assert "task PushTStandard, as the dataset records it" in err
    assert json.loads((tmp_path / "run" / "train_config.json").read_text())["task"] == "PushTStandard"


def test_a_dataset_says_which_task_it_holds(standard_demos, tmp_path):
    src, root = _export(standard_demos, tmp_path, "std")
    assert recorded_task(src) == recorded_task(root) == "PushTStandard"     # env_args env_name, robot_type
    (tmp_path / "junk.hdf5").write_bytes(b"not HDF5")
    assert recorded_task(tmp_path / "junk.hdf5") is None and recorded_task(tmp_path / "none.hdf5") is None


def test_a_training_refusal_names_trains_own_map_option(standard_demos, tmp_path, monkeypatch, capsys):
    """The refusal told `jepa-policy train` users to pass --map, which is `jepa-envs lerobot import`'s option;
    train's is --dataset-map (a JSON object)."""
    from jepa_policy.cli import main

    monkeypatch.setenv("JEPA_DATA_CACHE", str(tmp_path / "cache"))
    _, root = _export(standard_demos, tmp_path, "std")
    assert main(["train", "--preset", "quick", "--dataset", str(root), "--steps", "2", "--no-progress",
                 "--dataset-map", '{"observation.state": "nope"}']) == 2
    err = capsys.readouterr().err
    assert """--dataset-map '{"observation.state": "nope"}': 'nope' is not a key of task PushTStandard""" in err
    renamed = tmp_path / "renamed"
    shutil.copytree(root, renamed)
    info = json.loads((renamed / "meta/info.json").read_text())
    info["features"]["observation.pixels"] = info["features"].pop("observation.image")
    (renamed / "meta/info.json").write_text(json.dumps(info))
    assert main(["train", "--preset", "quick", "--dataset", str(renamed), "--steps", "2", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert """--dataset-map '{"FEATURE": "top_image"}'""" in err and "--map" not in err.replace("--dataset-map", "")
    message = refused(renamed, tmp_path, "has no feature 'observation.image'", task="PushTStandard")
    assert "--map FEATURE=top_image" in message       # jepa-envs lerobot import's own option, there


def test_frames_of_another_size_are_named(standard_demos, tmp_path):
    _, root = _export(standard_demos, tmp_path, "at84", image_size=84)
    message = refused(root, tmp_path, "does not fit task PushTStandard", task="PushTStandard")
    assert "observation.image is 84 x 84; the standard PushT observes 96 x 96 frames" in message


@pytest.mark.parametrize("scale, task", [(1 / 512, "PushTStandard"), (1 / 512, "PushT"), (2.0, "PushTStandard")])
def test_actions_in_other_units_are_named(standard_demos, tmp_path, scale, task):
    """Actions normalised to [0, 1] (or doubled, off the table) are not the agent position's table units."""
    _, root = _export(standard_demos, tmp_path, "scaled", action_scale=scale)
    message = refused(root, tmp_path, f"does not fit task {task}", task=task)
    assert "convert the actions to table units" in message and "actions span [" in message


def test_the_embedded_pusht_refuses_the_standard_layout_naming_the_task_to_pass(standard_demos, tmp_path):
    _, root = _export(standard_demos, tmp_path, "std")
    message = refused(root, tmp_path, "does not fit task PushT ", task="PushT")
    assert "laid out as LeRobot's lerobot/pusht (observation.image)" in message
    assert "pass --task PushTStandard" in message
    assert "convert the actions" not in message   # same table units in both variants
