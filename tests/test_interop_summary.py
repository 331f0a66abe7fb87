"""`make interop`'s summary (scripts/interop_summary.py): a part that crashed or did not run is a FAIL with its reason,
and a result of an earlier run is never shown as this run's. Needs none of the interop venvs."""
import json
from pathlib import Path
from script_loader import load_script

ROOT = Path(__file__).resolve().parents[1]
RUN = "20261206T180000Z-1"


def _summary():
    return load_script("interop_summary")


def _openpi(run_id=RUN, ok=True):
    return {"run_id": run_id, "ok": ok, "episodes": 2, "steps": 600, "max_abs_action_diff": 0.0,
            "refused_without_key": True}


def _record(run_id=RUN, exit_status=0):
    return {"part": "openpi", "run_id": run_id, "exit": exit_status, "seconds": 42}


def test_a_part_of_this_run_that_passed_shows_its_numbers_and_wall_time():
    row = _summary().part_row("openpi", RUN, _record(), _openpi())
    assert row["ok"] and row["seconds"] == 42
    assert "2 episodes, 600 steps" in row["numbers"] and "max |served - in-process action| 0" in row["numbers"]


def test_a_part_that_crashed_or_never_ran_is_a_fail_with_the_reason():
    s = _summary()
    crashed = s.part_row("openpi", RUN, _record(exit_status=1), None, "RuntimeError: jepa-policy serve did not start")
    assert not crashed["ok"] and crashed["seconds"] == 42
    assert crashed["numbers"] == "no result (exit 1: RuntimeError: jepa-policy serve did not start)"
    never = s.part_row("openpi", RUN, None, None)
    assert not never["ok"] and never["numbers"] == "did not run in this run"
    failed = s.part_row("openpi", RUN, _record(exit_status=1), _openpi(ok=False))
    assert not failed["ok"] and failed["numbers"].endswith("(exit 1)")
    # a result that says ok from a part whose process then failed is not a pass either
    assert not s.part_row("openpi", RUN, _record(exit_status=1), _openpi())["ok"]


def test_an_earlier_runs_result_is_not_shown_as_this_runs():
    s = _summary()
    stale = s.part_row("openpi", RUN, _record(exit_status=137), _openpi(run_id="20261205T090000Z-7"), "Killed")
    assert not stale["ok"]
    assert stale["numbers"] == "no result from this run, only run 20261205T090000Z-7's (exit 137: Killed)"
    old_record = s.part_row("openpi", RUN, _record(run_id="20261205T090000Z-7"), _openpi(run_id="20261205T090000Z-7"))
    assert not old_record["ok"] and "not run in this run" in old_record["numbers"]
    by_hand = s.part_row("openpi", RUN, _record(), _openpi(run_id=None))   # the script run alone has no run id
    assert not by_hand["ok"] and "only run None's" in by_hand["numbers"]


def test_the_table_lists_every_part_from_the_files_and_fails_the_missing_ones(tmp_path):
    s = _summary()
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "openpi.json").write_text(json.dumps(_record()))
    (tmp_path / "openpi.json").write_text(json.dumps(_openpi()))
    (tmp_path / "parts" / "robomimic.json").write_text(json.dumps({**_record(exit_status=1), "part": "robomimic"}))
    (tmp_path / "parts" / "robomimic.log").write_text("table...\nValueError: boom\n\n")
    rows = s.collect(tmp_path, RUN)
    assert [r["name"] for r in rows] == ["LeRobot data", "LeRobot plugin", "openpi", "gym-pusht", "robomimic"]
    assert [r["ok"] for r in rows] == [False, False, True, False, False]
    assert rows[4]["numbers"] == "no result (exit 1: ValueError: boom)"
    lines = s.table(rows)
    assert len(lines) == 2 + 5 and lines[4].startswith("| openpi | pass |") and lines[4].endswith("| 42 s |")
    assert lines[2] == "| LeRobot data | FAIL | did not run in this run | - |"
    assert "max \\|served - in-process action\\| 0" in lines[4]   # escaped inside the markdown cell


def test_a_result_that_is_not_an_object_or_has_wrong_types_is_a_fail_not_a_crash(tmp_path):
    s = _summary()
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "openpi.json").write_text(json.dumps(_record()))
    (tmp_path / "openpi.json").write_text(json.dumps([RUN, True]))          # valid JSON, not an object
    (tmp_path / "parts" / "gym-pusht.json").write_text(json.dumps({**_record(), "part": "gym-pusht"}))
    (tmp_path / "pusht.json").write_bytes(b"\xff\xfe not text")
    rows = {r["part"]: r for r in s.collect(tmp_path, RUN)}
    assert not rows["openpi"]["ok"] and rows["openpi"]["numbers"] == "no result (exit 0)"
    assert not rows["gym-pusht"]["ok"] and rows["gym-pusht"]["numbers"].startswith("no result")
    # a list where the robomimic part writes its per-task object: AttributeError, read as unreadable
    wrong = s.part_row("robomimic", RUN, {**_record(), "part": "robomimic"}, {"run_id": RUN, "ok": True, "tasks": []})
    assert not wrong["ok"] and wrong["numbers"].startswith("result unreadable"), wrong
