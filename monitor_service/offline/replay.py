"""Recorded rollouts into a running monitor through its public HTTP API (``jepa-monitor replay``).

A records file is ``jepa-policy eval --keep-latents --out FILE`` (or the pick job's ``decisions.jsonl.gz``):
one JSON object per episode with its ``success``, ``length`` (env steps) and ``decisions``, each scored decision
holding the predicted latent ``z_hat`` for its ``target_step``, the current latent ``z_now`` and the realized
``z_real``. Each episode is sent as a robot sends it, with ``MonitorClient``: its decisions (z_hat, z_now and the
named scores the task registered), the realized latents at their target steps, then its outcome. A decision whose
target never came (the episode ended first) is sent without one, as on the robot.

Which episodes calibrate: ``held_out`` (the first N episodes of the file, in its order, or a share of them) are
sent as held-out labelled rollouts; the rest as live episodes, scored and alerted on by the task's calibration.
"""
from __future__ import annotations

import gzip
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import httpx
from tqdm import tqdm

from monitor_service.client import MonitorClient


def read_records(path: str | Path, where: dict[str, str] | None = None) -> list[dict]:
    """The episode records of a JSONL file (``.gz``: gzip), those whose fields equal ``where`` (as strings).
    Raises ValueError naming the line of a record that is not an episode with latents."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist; write one with `jepa-policy eval --keep-latents --out "
                                f"{path.name}`")
    opener = gzip.open if path.suffix == ".gz" else open
    out = []
    number = 0
    try:
        with opener(path, "rt") as f:
            for number, line in enumerate(f, 1):
                row = _record(path, number, line, where)
                if row is not None:
                    out.append(row)
    except (OSError, EOFError, UnicodeDecodeError) as exc:   # gzip.BadGzipFile is an OSError
        raise ValueError(f"{path}: unreadable after line {number} ({type(exc).__name__}: {exc}); give an intact "
                         "records file (JSONL, or gzip-compressed .jsonl.gz)") from None
    return out


def _record(path: Path, number: int, line: str, where: dict[str, str] | None) -> dict | None:
    """One line of a records file: its episode record, or None when blank or filtered out."""
    if not line.strip():
        return None
    try:
        row = json.loads(line)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}:{number}: not JSON ({exc.msg})") from None
    if not isinstance(row, dict) or "success" not in row or not isinstance(row.get("decisions"), list):
        raise ValueError(f"{path}:{number}: not an episode record (needs success and decisions)")
    if where and any(str(row.get(k)) != v for k, v in where.items()):
        return None
    if not any(isinstance(d, dict) and "z_hat" in d for d in row["decisions"]):
        raise ValueError(f"{path}:{number}: its decisions hold no latents (z_hat); record them with "
                         "`jepa-policy eval --keep-latents`")
    return row


@dataclass
class ReplaySummary:
    task: str
    episodes: int = 0
    held_out: int = 0
    decisions: int = 0
    targets: int = 0
    in_flight: int = 0     # live episodes sent without their outcome
    dropped: int = 0
    rejected: list[str] = field(default_factory=list)   # the service's refusals, one line each
    episode_ids: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "episode_ids"}


def send_episode(client: MonitorClient, task: str, episode_id: str, record: dict, held_out: bool,
                 checkpoint: str | None = None, group: str | None = None,
                 signals: tuple[str, ...] = (), outcome: bool = True) -> tuple[int, int]:
    """One episode in the robot's order: every decision, then each realized latent once its step is reached,
    then the outcome (``outcome`` False: none, the episode still running as the service sees it). ``signals``:
    the named scores to send with the decisions (those the task registered). Returns (decisions, targets)
    queued."""
    decisions = sorted((d for d in record["decisions"] if "z_hat" in d), key=lambda d: d["step"])
    realized = {}
    for d in decisions:
        scores = {s: float(v) for s, v in (d.get("scores") or {}).items() if s in signals and v is not None}
        client.decision(task, episode_id, int(d["step"]), int(d["target_step"]) - int(d["step"]), d["z_hat"],
                        checkpoint=checkpoint, held_out=held_out, group=group, z_now=d.get("z_now"),
                        scores=scores or None)
        if d.get("z_real") is not None:
            realized[int(d["target_step"])] = d["z_real"]
    for step in sorted(realized):
        client.target(episode_id, step, realized[step])
    if outcome:
        client.outcome(episode_id, bool(record["success"]), held_out=held_out, group=group,
                       length=None if record.get("length") is None else int(record["length"]))
    return len(decisions), len(realized)


PARTS = ("all", "held-out", "live")


def episode_id(record: dict, i: int, prefix: str = "") -> str:
    """``prefix`` + the record's ``episode_id``, or its seed (after its fault's name when it ran under one, as
    ``jepa-policy eval --faults`` records the same seeds once per fault), or its place in the file."""
    base = record.get("episode_id")
    if base is None:
        regime = record.get("regime")
        base = (f"{regime}-" if regime not in (None, "natural") else "") + str(record.get("seed", i))
    return f"{prefix}{base}"


def check_service(url: str) -> None:
    """ValueError naming the fix when no ready monitor answers at ``url``."""
    try:
        status = httpx.get(url.rstrip("/") + "/readyz", timeout=5.0).status_code
    except httpx.HTTPError as exc:
        raise ValueError(f"no monitor answers at {url} ({type(exc).__name__}); start one with `jepa-monitor "
                         "serve` or give its address with --url") from None
    if status != 200:
        raise ValueError(f"the monitor at {url} is not ready (GET /readyz answered HTTP {status}); see its log")


def replay(records: list[dict], url: str, api_key: str, task: str, held_out: int, robot: str | None = None,
           prefix: str = "", checkpoint: str | None = None, group: str | None = None,
           signals: tuple[str, ...] = (), timeout: float = 120.0, progress: bool = False,
           part: str = "all", in_flight: int = 0) -> ReplaySummary:
    """Send ``records`` to the monitor at ``url`` with a robot key: the first ``held_out`` as held-out labelled
    rollouts, the rest live (``part``: only the held-out ones, or only the live ones, e.g. after calibrating on
    the former). Episode ids: ``episode_id``. Raises ValueError when no monitor answers or it refuses every
    record of the first episode sent (a wrong task, key or robot: nothing more is sent), RuntimeError when it
    did not take every record within ``timeout`` seconds. ``progress``: a bar of the episodes on stderr.
    ``in_flight``: the last that many live episodes are sent without their outcome, so that the service (and
    its dashboard) sees them running until its live window passes."""
    if part not in PARTS:
        raise ValueError(f"part {part!r}: choose one of {', '.join(PARTS)}")
    chosen = {"all": range(len(records)), "held-out": range(min(held_out, len(records))),
              "live": range(min(held_out, len(records)), len(records))}[part]
    n_live = sum(i >= held_out for i in chosen)
    if not 0 <= in_flight <= n_live:
        raise ValueError(f"in_flight {in_flight}: give 0 to {n_live}, the live episodes sent (held-out ones always "
                         "carry their outcome, which calibration needs)")
    check_service(url)
    summary = ReplaySummary(task)
    client_log = logging.getLogger("monitor_service.client")
    level = client_log.level
    client_log.setLevel(logging.ERROR)   # refusals are counted and reported here, not one log line each
    try:
        with MonitorClient(url, api_key, robot=robot, batch_size=512) as client:
            for k, i in enumerate(tqdm(chosen, desc=f"replay {task}", unit="episode", disable=not progress)):
                eid = episode_id(records[i], i, prefix)
                n_dec, n_tgt = send_episode(client, task, eid, records[i], i < held_out, checkpoint, group, signals,
                                            outcome=k < len(chosen) - in_flight)
                summary.episodes += 1
                summary.held_out += i < held_out
                summary.in_flight += k >= len(chosen) - in_flight
                summary.decisions += n_dec
                summary.targets += n_tgt
                summary.episode_ids.append(eid)
                if k == 0 or client.pending > client.max_buffer // 2:   # never drop a record
                    if not client.flush(timeout):
                        break
                if k == 0 and len(client.stats.rejected) >= n_dec + n_tgt + 1:
                    rec, status, detail = client.stats.rejected[0]
                    raise ValueError(f"the monitor refused every record of the first episode ({rec['kind']}: HTTP "
                                     f"{status} {' '.join(str(detail).split())[:300]}); check --task, the key (a "
                                     "robot key) and --robot")
            if not client.flush(timeout):
                raise RuntimeError(f"the monitor at {url} took not all records within {timeout:g} s "
                                   f"({client.pending} pending); is it still running?")
            summary.dropped = client.stats.dropped
            summary.rejected = [f"{rec['kind']} {rec.get('episode')} step {rec.get('step')}: HTTP {status} "
                                f"{' '.join(str(detail).split())[:300]}"
                                for rec, status, detail in client.stats.rejected]
    finally:
        client_log.setLevel(level)
    return summary
