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
from dataclasses import dataclass, field
from pathlib import Path

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
    with opener(path, "rt") as f:
        for number, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError as exc:
                raise ValueError(f"{path}:{number}: not JSON ({exc.msg})") from None
            if not isinstance(row, dict) or "success" not in row or not isinstance(row.get("decisions"), list):
                raise ValueError(f"{path}:{number}: not an episode record (needs success and decisions)")
            if where and any(str(row.get(k)) != v for k, v in where.items()):
                continue
            if not any("z_hat" in d for d in row["decisions"]):
                raise ValueError(f"{path}:{number}: its decisions hold no latents (z_hat); record them with "
                                 "`jepa-policy eval --keep-latents`")
            out.append(row)
    return out


@dataclass
class ReplaySummary:
    task: str
    episodes: int = 0
    held_out: int = 0
    decisions: int = 0
    targets: int = 0
    dropped: int = 0
    rejected: list[str] = field(default_factory=list)   # the service's refusals, one line each
    episode_ids: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "episode_ids"}


def send_episode(client: MonitorClient, task: str, episode_id: str, record: dict, held_out: bool,
                 checkpoint: str | None = None, group: str | None = None,
                 signals: tuple[str, ...] = ()) -> tuple[int, int]:
    """One episode in the robot's order: every decision, then each realized latent once its step is reached,
    then the outcome. ``signals``: the named scores to send with the decisions (those the task registered).
    Returns (decisions, targets) queued."""
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
    client.outcome(episode_id, bool(record["success"]), held_out=held_out, group=group,
                   length=None if record.get("length") is None else int(record["length"]))
    return len(decisions), len(realized)


def replay(records: list[dict], url: str, api_key: str, task: str, held_out: int, robot: str = "replay",
           prefix: str = "", checkpoint: str | None = None, group: str | None = None,
           signals: tuple[str, ...] = (), timeout: float = 120.0, progress: bool = False) -> ReplaySummary:
    """Send ``records`` to the monitor at ``url`` with a robot key: the first ``held_out`` as held-out labelled
    rollouts, the rest live. Episode ids are ``prefix`` + the record's ``episode_id`` (or its seed). Raises
    RuntimeError when the service did not take every record within ``timeout`` seconds. ``progress``: a bar of
    the episodes queued on stderr."""
    summary = ReplaySummary(task)
    with MonitorClient(url, api_key, robot=robot, batch_size=512) as client:
        for i, record in enumerate(tqdm(records, desc=f"replay {task}", unit="episode", disable=not progress)):
            eid = f"{prefix}{record.get('episode_id') or record.get('seed', i)}"
            n_dec, n_tgt = send_episode(client, task, eid, record, i < held_out, checkpoint, group, signals)
            summary.episodes += 1
            summary.held_out += i < held_out
            summary.decisions += n_dec
            summary.targets += n_tgt
            summary.episode_ids.append(eid)
            if client.pending > client.max_buffer // 2 and not client.flush(timeout):   # never drop a record
                break
        if not client.flush(timeout):
            raise RuntimeError(f"the monitor at {url} took not all records within {timeout:g} s "
                               f"({client.pending} pending); is it running, and is the key a robot key?")
        summary.dropped = client.stats.dropped
        summary.rejected = [f"{rec['kind']} {rec.get('episode')} step {rec.get('step')}: HTTP {status} {detail}"
                            for rec, status, detail in client.stats.rejected]
    return summary
