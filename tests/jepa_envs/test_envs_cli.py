"""The jepa-envs command line."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from jepa_envs.cli import main
from jepa_envs.datasets.hdf5 import load_dataset
from jepa_envs.tasks.spec import all_task_specs


def test_make_demos_writes_a_loadable_file(tmp_path, capsys):
    out = tmp_path / "demos.hdf5"
    assert main(["make-demos", "PushT", "--episodes", "2", "--out", str(out), "--seed", "5",
                 "--image-size", "32"]) == 0
    printed, err = capsys.readouterr()
    assert "wrote 2 demos" in printed and "PushT demos: 100%" in err     # the bar, on stderr
    assert main(["make-demos", "PushT", "--episodes", "2", "--out", str(tmp_path / "again.hdf5"), "--seed", "5",
                 "--image-size", "32", "--no-progress"]) == 0
    assert capsys.readouterr().err == ""
    ds = load_dataset(out, cache_dir=False)
    assert ds.num_episodes() == 2 and ds.spec.name == "PushT"
    assert ds.obs["top_image"].shape[1:] == (32, 32, 3)
    assert ds.env_args["env_kwargs"]["image_size"] == 32 and ds.env_args["expert"]["seed"] == 5


def test_make_demos_is_reproducible_for_a_seed(tmp_path):
    paths = [tmp_path / f"{i}.hdf5" for i in range(2)]
    for p in paths:
        main(["make-demos", "PushT", "--episodes", "1", "--out", str(p), "--seed", "3", "--image-size", "16"])
    a, b = (load_dataset(p, cache_dir=False) for p in paths)
    assert (a.actions == b.actions).all() and (a.obs["top_image"] == b.obs["top_image"]).all()


def test_make_demos_errors_name_the_problem(tmp_path):
    with pytest.raises(SystemExit, match="no scripted expert exists for Square"):
        main(["make-demos", "Square", "--episodes", "1", "--out", str(tmp_path / "x.hdf5")])
    with pytest.raises(SystemExit, match="unknown task 'Nope'"):
        main(["make-demos", "Nope", "--episodes", "1", "--out", str(tmp_path / "x.hdf5")])
    with pytest.raises(SystemExit, match="--episodes must be >= 1"):
        main(["make-demos", "PushT", "--episodes", "0", "--out", str(tmp_path / "x.hdf5")])
    with pytest.raises(SystemExit, match=r"error: finish_threshold must lie between .* \(0.8\) and 1, got 0.5"):
        main(["make-demos", "PushT", "--episodes", "1", "--out", str(tmp_path / "x.hdf5"), "--finish-threshold", "0.5"])
    assert not (tmp_path / "x.hdf5").exists()


def test_list_and_info(capsys):
    assert main(["list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    pusht = next(line for line in lines if line.startswith("PushT "))
    assert "JEPA/PushT-v0" in pusht and "available" in pusht and "unavailable" not in pusht
    assert len(lines) == 1 + len(all_task_specs())  # header + one line per registered task
    assert main(["info", "JEPA/PushT-v0"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["name"] == "PushT" and data["action_dim"] == 2 and data["backend_available"] is True


def test_bench_prints_a_row_per_task(capsys):
    assert main(["bench", "--tasks", "PushT", "--steps", "64", "--seconds", "2"]) == 0
    out, err = capsys.readouterr()
    assert "jepa-envs bench: 100%" in err and "1/1" in err
    row = next(line for line in out.splitlines() if line.startswith("PushT "))
    raw, ours = (float(v) for v in row.split()[1:3])
    assert raw > 0 and ours > 0 and row.split()[3].endswith("%")   # the overhead column (the load follows)


GYM_PUSHT_PYTHON = Path(__file__).resolve().parents[2] / ".cache" / "interop" / "gym_pusht" / "bin" / "python"


def test_bench_against_gym_pusht_refuses_an_interpreter_without_it_in_one_line(capsys):
    assert main(["bench", "--gym-pusht", sys.executable]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "gym-pusht did not start in" in err[-1] and "No module named 'gym_pusht'" in err[-1]   # below the bar
    assert main(["bench", "--gym-pusht", sys.executable, "--no-progress"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == err[-1:]


@pytest.mark.skipif(not GYM_PUSHT_PYTHON.exists(), reason="gym-pusht's venv is built by `make interop`")
def test_bench_against_gym_pusht_prints_both_rates_per_obs_type(capsys):
    from jepa_envs.bench import bench_gym_pusht

    rows = bench_gym_pusht(str(GYM_PUSHT_PYTHON), steps=100, budget_s=2.0)
    assert [r["obs_type"] for r in rows] == ["pixels_agent_pos", "state"]
    for r in rows:
        assert r["gym_pusht"] > 0 and r["ours"] > 0 and r["ratio"] == pytest.approx(r["ours"] / r["gym_pusht"])
        assert r["blocks"] >= 1 and len(r["load"]) == 2
