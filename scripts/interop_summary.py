"""`make interop`, last step: one table of every part of this run, with pass/fail, its key numbers and wall time.

scripts/interop.sh runs each part through its ``part`` function, which writes interop_out/parts/<part>.json (this
run's id, the exit status, the wall time, the load before and after) and keeps the part's output in
interop_out/parts/<part>.log; each part's script writes its own result (``RESULTS`` below) with the run id it was
given in ``INTEROP_RUN_ID``. A part whose record or result is missing or carries another run's id is a FAIL with the
reason (the last line of its output, or the other run's id): nothing of an earlier run is shown as this run's.

    python scripts/interop_summary.py --run-id ID --seconds N [--out interop_out]

Prints the table (markdown), writes interop_out/summary.json. Exit 1 unless every part passed.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

# part -> (its row's name, its result file under the output folder)
RESULTS = {
    "lerobot-data": ("LeRobot data", "lerobot.json"),
    "lerobot-plugin": ("LeRobot plugin", "lerobot_policy/lerobot_policy.json"),
    "openpi": ("openpi", "openpi.json"),
    "gym-pusht": ("gym-pusht", "pusht.json"),
    "robomimic": ("robomimic", "robomimic.json"),
}


def _g(x: float | None) -> str:
    return "-" if x is None else "0" if x == 0 else f"{x:.1e}"


def _eq(ok: bool) -> str:
    return "equal" if ok else "DIFFER"


def _trains(ok: bool) -> str:
    return "trains" if ok else "does NOT train"


def lerobot_data(r: dict) -> str:
    read, written, layout = r["read_by_lerobot"], r["written_by_lerobot"], r["lerobot_pusht_layout"]
    refused = sum(x["exit"] != 0 and x["lines"] == 1 for x in layout["refusals"].values())
    return (f"ours -> LeRobotDataset: lossless frames {_eq(read['lossless']['frames_equal'])}, AV1 PSNR "
            f"{read['av1']['frames']['psnr_db']} dB, actions/state/indices {_eq(read['lossless']['ok'])}; "
            f"LeRobotDataset.create -> ours: actions {_eq(written['actions_equal'])}, PSNR "
            f"{written['frames']['psnr_db']} dB, {_trains(written['train_from_root'])}; lerobot/pusht layout: actions "
            f"{_eq(layout['actions_equal'])}, {_trains(layout['train_from_root'])}, refusals {refused}/"
            f"{len(layout['refusals'])} in one line")


def lerobot_plugin(r: dict) -> str:
    train, ev, back, conv = r["train_jepa"], r["eval_lerobot"], r["lerobot_to_ours"], r["ours_to_lerobot"]
    return (f"lerobot-train {train['steps']} steps (loss {train['losses'][-1][1]:.3f}), MIP {r['train_mip']['steps']}; "
            f"lerobot-eval {ev['episodes']} episodes, {ev['pc_success']:.0f} % success; max |action diff| on "
            f"{back['observations']:,} obs: LeRobot's checkpoint in ours {_g(back['max_abs_action_diff'])} (z_hat "
            f"{_g(back['max_abs_z_hat_diff'])}), ours in LeRobot {_g(conv['max_abs_action_diff'])}, MIP "
            f"{_g(r['mip_lerobot_to_ours']['max_abs_action_diff'])}; loads both ways (jepa-policy eval "
            f"{back['jepa_policy_eval']['episodes']} episodes, serve ready, lerobot-eval of ours "
            f"{conv['lerobot_eval']['episodes']} episodes)")


def openpi(r: dict) -> str:
    refused = "refused" if r["refused_without_key"] else "NOT refused"
    return (f"openpi-client 0.1.2, {r['episodes']} episodes, {r['steps']} steps: max |served - in-process action| "
            f"{_g(r['max_abs_action_diff'])}; {refused} without the API key")


def gym_pusht(r: dict) -> str:
    parts = []
    for name in ("random", "expert", "reset_to_state"):
        s = r[name]["summary"]["pymunk7"]
        parts.append(f"{name} {s['episodes_within_tol']}/{s['episodes']}")
    frames = sum(r[n]["summary"]["pymunk7"]["frames_equal"] for n in ("random", "expert", "reset_to_state"))
    total = sum(r[n]["summary"]["pymunk7"]["frames"] for n in ("random", "expert", "reset_to_state"))
    return (f"{r['seeds']} seeds x {r['steps']} steps; episodes within 1e-6 of gym-pusht's state: "
            f"{', '.join(parts)}; pixels identical {frames:,}/{total:,}; step speed ours / gym-pusht "
            f"{r['speed']['ratio_pixels_agent_pos_cpu']:.2f}x (CPU)")


def robomimic(r: dict) -> str:
    tasks = r["tasks"]
    image = lambda rows: max(d["max"] for d in rows.values() if d.get("kind") == "image")   # noqa: E731
    low = lambda rows: max(d["max"] for d in rows.values() if d.get("kind") == "low-dim")   # noqa: E731
    obs = ", ".join(f"{t} {'pass' if all(d['ok'] for d in x['obs'].values()) else 'FAIL'} ({x['states']} states)"
                    for t, x in tasks.items())
    text = (f"observations: {obs}, pixels max {max(image(x['obs']) for x in tasks.values())}, low-dim max "
            f"{_g(max(low(x['obs']) for x in tasks.values()))}")
    d = r.get("datasets")
    if d:
        files = d["files"]["as recorded"]
        frames = max(row["frames"] for row in files["keys"].values())
        text += (f"; render-dataset vs dataset_states_to_obs: {len(files['demos'])} "
                 f"demos, {frames:,} frames, {'equal' if files['ok'] else 'DIFFER'} (pixels max "
                 f"{max(row['max'] for k, row in files['keys'].items() if k.endswith('image'))})")
    # delta -> absolute against robosuite's goals in robomimic's replay (steps 1 on; step 0 is explained in its table)
    later = [x["actions"]["later"] for x in tasks.values()] + [a["converted"]["later"] for a in
                                                               (d or {}).get("actions", [])]
    angles = [a["orientation_max_rad"] for a in later if a["orientation_max_rad"] is not None]
    return (f"{text}; actions: goal position max {_g(max(a['position_max_m'] for a in later))} m, orientation max "
            f"{_g(max(angles, default=None))} rad")


NUMBERS = {"lerobot-data": lerobot_data, "lerobot-plugin": lerobot_plugin, "openpi": openpi, "gym-pusht": gym_pusht,
           "robomimic": robomimic}


def part_row(part: str, run_id: str, record: dict | None, result: dict | None, last_line: str = "") -> dict:
    """One row: PASS only when this run's record and this run's result say so; otherwise FAIL and why."""
    row = {"part": part, "name": RESULTS[part][0], "seconds": None, "ok": False}
    if record is None or record.get("run_id") != run_id:
        row["numbers"] = ("did not run in this run" if record is None else
                          f"not run in this run (its record is run {record.get('run_id')}'s)")
        return row
    row["seconds"] = record["seconds"]
    crashed = f"exit {record['exit']}" + (f": {last_line[:200]}" if last_line else "")
    if result is None:
        row["numbers"] = f"no result ({crashed})"
        return row
    if result.get("run_id") != run_id:
        row["numbers"] = f"no result from this run, only run {result.get('run_id')}'s ({crashed})"
        return row
    try:
        row["numbers"] = NUMBERS[part](result)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:
        row["numbers"] = f"result unreadable ({type(e).__name__}: {e})"
        return row
    row["ok"] = bool(result.get("ok")) and record["exit"] == 0
    if not row["ok"]:
        row["numbers"] += f" ({crashed if record['exit'] else 'a check failed, see its table above'})"
    return row


def _json(path: Path) -> dict | None:
    """The JSON object in ``path``; None when it is missing, unreadable or not an object (a FAIL row then)."""
    try:
        value = json.loads(path.read_text())
    except (FileNotFoundError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return value if isinstance(value, dict) else None


def _last_line(path: Path) -> str:
    try:
        lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()]
    except FileNotFoundError:
        return ""
    return lines[-1].strip() if lines else ""


def collect(out: Path, run_id: str) -> list[dict]:
    return [part_row(part, run_id, _json(out / "parts" / f"{part}.json"), _json(out / result),
                     _last_line(out / "parts" / f"{part}.log")) for part, (_, result) in RESULTS.items()]


def table(rows: list[dict]) -> list[str]:
    lines = ["| part | result | key numbers | wall time |", "|---|---|---|---|"]
    for r in rows:
        seconds = "-" if r["seconds"] is None else f"{r['seconds']:,} s"
        numbers = r["numbers"].replace("|", "\\|")   # |x| inside a markdown cell
        lines.append(f"| {r['name']} | {'pass' if r['ok'] else 'FAIL'} | {numbers} | {seconds} |")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-id", required=True, help="the id scripts/interop.sh gave this run")
    parser.add_argument("--seconds", type=int, required=True, help="the run's wall time so far")
    parser.add_argument("--load", default="", help="the load average at the run's start")
    parser.add_argument("--out", type=Path, default=Path("interop_out"))
    args = parser.parse_args()
    rows = collect(args.out, args.run_id)
    ok = all(r["ok"] for r in rows)
    load_end = " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else ""
    print(f"\nmake interop, run {args.run_id}: {sum(r['ok'] for r in rows)}/{len(rows)} parts passed")
    print("\n".join(table(rows)))
    print(f"total wall time {args.seconds:,} s; load average {args.load or '?'} at the start, {load_end or '?'} "
          f"at the end")
    (args.out / "summary.json").write_text(json.dumps({"run_id": args.run_id, "seconds": args.seconds,
                                                       "load_start": args.load, "load_end": load_end, "ok": ok,
                                                       "parts": rows}, indent=2))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
