"""Per-episode records: observations at decision frames, actions, timing, outcome and the evaluation manifest;
and the newest frames the bridge serves (``FrameHistory``).

Each finished episode becomes ``<root>/<task>/<episode_id>.h5`` (arrays) plus ``<episode_id>.json`` (the
evaluation manifest: policy checkpoint, seed, outcome, chunk budget, latency summary, safety events), so a
result can be audited later without the robot.
"""
from __future__ import annotations

import collections
import json
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

OUTCOMES = ("success", "failure", "interrupted")


def check_manifest(manifest) -> dict:
    """The client's episode manifest as the record will store it, or ValueError naming what JSON cannot hold.

    Checked when the episode starts (``reset``), so a bad value is refused before anything moves instead of
    losing the episode's record at its end.
    """
    if not isinstance(manifest, dict):
        raise ValueError(f"manifest must be a map, got {type(manifest).__name__}")
    try:
        json.dumps(manifest, allow_nan=False)
    except (TypeError, ValueError, OverflowError, RecursionError) as exc:
        raise ValueError(f"the manifest cannot be stored in the episode's JSON record ({str(exc)[:120]}); send "
                         "strings, finite numbers, booleans, null, lists and maps with string keys") from None
    return manifest


def latency_stats(latencies_s, skip_first: bool = True) -> dict:
    """Median and p95 frame-to-chunk latency in ms; the paper drops each episode's first chunk (Sec. 4.8)."""
    values = np.asarray(latencies_s, dtype=np.float64)
    if skip_first and values.size > 1:
        values = values[1:]
    if values.size == 0:
        return {"count": 0, "median_ms": None, "p95_ms": None}
    return {
        "count": int(values.size),
        "median_ms": float(np.median(values) * 1e3),
        "p95_ms": float(np.percentile(values, 95) * 1e3),
    }


@dataclass
class EpisodeRecord:
    """Everything logged for one episode while it runs; ``save`` writes it to disk."""

    task: str
    chunk_budget: int
    action_dim: int
    manifest: dict = field(default_factory=dict)
    episode_id: str = field(default_factory=lambda: time.strftime("%Y%m%d-%H%M%S-") + uuid.uuid4().hex[:8])
    started_at: float = field(default_factory=time.time)
    decision_steps: list[int] = field(default_factory=list)
    decision_obs: list[dict] = field(default_factory=list)
    requested: list[np.ndarray] = field(default_factory=list)
    executed: list[np.ndarray] = field(default_factory=list)
    action_times: list[float] = field(default_factory=list)
    chunk_latency_s: list[float] = field(default_factory=list)
    safety_events: list[dict] = field(default_factory=list)
    steps: int = 0
    chunks: int = 0
    outcome: str | None = None
    reason: str = ""
    ended_at: float | None = None

    def add_decision_frame(self, obs: dict[str, np.ndarray], step: int | None = None) -> None:
        """Log the frame a decision was made from (``step``: its episode step; default the current one)."""
        self.decision_steps.append(self.steps if step is None else int(step))
        self.decision_obs.append({k: np.array(v, copy=True) for k, v in obs.items()})

    def add_action(self, requested: np.ndarray, executed: np.ndarray | None) -> None:
        self.requested.append(np.asarray(requested, np.float64))
        self.executed.append(np.full_like(self.requested[-1], np.nan) if executed is None
                             else np.asarray(executed, np.float64))
        self.action_times.append(time.time())
        if executed is not None:
            self.steps += 1

    def chunk_arrived(self, latency_s: float) -> bool:
        """Count one chunk and its frame-to-chunk latency; True when it is a steady-state one (not the first)."""
        self.chunks += 1
        self.chunk_latency_s.append(latency_s)
        return self.chunks > 1

    def add_safety_event(self, step: int, report: dict) -> None:
        self.safety_events.append({"step": int(step), **report})

    @property
    def finished(self) -> bool:
        return self.outcome is not None

    def finish(self, outcome: str, reason: str = "") -> None:
        if outcome not in OUTCOMES:
            raise ValueError(f"episode outcome must be one of {OUTCOMES}, got {outcome!r}")
        if self.finished:
            return
        self.outcome, self.reason, self.ended_at = outcome, reason, time.time()

    def summary(self) -> dict:
        return {
            "episode_id": self.episode_id,
            "task": self.task,
            "outcome": self.outcome,
            "is_success": self.outcome == "success",
            "reason": self.reason,
            "steps": self.steps,
            "chunks": self.chunks,
            "chunk_budget": self.chunk_budget,
            "started_at": self.started_at,
            "ended_at": self.ended_at,
            "frame_to_chunk_latency": latency_stats(self.chunk_latency_s),
            "safety_events": self.safety_events,
            "manifest": self.manifest,
        }

    def save(self, root: str | Path) -> Path:
        """Write the HDF5 arrays and the JSON manifest; returns the manifest path.

        Both files appear complete or not at all: each is written under a temporary name and renamed, the JSON
        text is made before either is written, and a failure removes what was written.
        """
        folder = Path(root) / self.task
        folder.mkdir(parents=True, exist_ok=True)
        h5_path = folder / f"{self.episode_id}.h5"
        manifest_path = folder / f"{self.episode_id}.json"
        manifest_text = json.dumps({**self.summary(), "arrays": h5_path.name}, indent=2)
        summary_text = json.dumps(self.summary())
        tmp_h5, tmp_json = h5_path.with_suffix(".h5.tmp"), manifest_path.with_suffix(".json.tmp")
        try:
            self._write_arrays(tmp_h5, summary_text)
            tmp_json.write_text(manifest_text)
            tmp_h5.replace(h5_path)
            tmp_json.replace(manifest_path)
        except BaseException:
            for path in (tmp_h5, tmp_json):
                path.unlink(missing_ok=True)
            raise
        return manifest_path

    def _write_arrays(self, path: Path, summary_text: str) -> None:
        with h5py.File(path, "w") as f:
            f.create_dataset("decision_steps", data=np.asarray(self.decision_steps, np.int64))
            obs_group = f.create_group("obs")
            for key in (self.decision_obs[0] if self.decision_obs else {}):
                data = np.stack([o[key] for o in self.decision_obs])
                obs_group.create_dataset(key, data=data, compression="gzip" if data.dtype == np.uint8 else None)
            width = self.action_dim
            f.create_dataset("actions_requested", data=np.asarray(self.requested, np.float64).reshape(-1, width))
            f.create_dataset("actions_executed", data=np.asarray(self.executed, np.float64).reshape(-1, width))
            f.create_dataset("action_times", data=np.asarray(self.action_times, np.float64))
            f.create_dataset("chunk_latency_s", data=np.asarray(self.chunk_latency_s, np.float64))
            f.attrs["summary"] = summary_text


class FrameHistory:
    """The newest observations with the episode step and the time each was taken (oldest dropped first): what
    ``observe`` serves, and the decision frame a streamed chunk was predicted from."""

    def __init__(self, size: int):
        self.recent: collections.deque = collections.deque(maxlen=size)   # (step, time, obs)
        self.obs: dict | None = None
        self.info: dict = {}
        self.time = 0.0

    def reset(self, obs: dict, info: dict) -> None:
        self.recent.clear()
        self.add(0, obs, info)

    def add(self, step: int, obs: dict, info: dict) -> None:
        self.time = time.monotonic()
        self.obs, self.info = obs, info
        self.recent.append((step, self.time, obs))

    def newest(self, history: int) -> list[tuple[int, float, dict]]:
        """The newest ``history`` frames, oldest first, padded with the oldest (as in training); [] when none."""
        frames = list(self.recent)[-history:]
        return [frames[0]] * (history - len(frames)) + frames if frames else []

    def at(self, step: int) -> tuple[float, dict]:
        """(time, observation) of the frame of ``step``, or of the newest when it is no longer kept."""
        return next(((t, o) for s, t, o in reversed(self.recent) if s == step), (self.time, self.obs))


def load_episode(manifest_path: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a saved episode back: (manifest, arrays) with arrays keyed like the HDF5 file (obs/<key> ...)."""
    manifest_path = Path(manifest_path)
    try:
        manifest = json.loads(manifest_path.read_bytes())
    except (ValueError, RecursionError) as exc:   # bad JSON or UTF-8; nested too deep for the parser
        why = "nested too deeply" if isinstance(exc, RecursionError) else f"not valid JSON ({str(exc)[:120]})"
        raise ValueError(f"episode manifest {manifest_path} is {why}; pass the .json a bridge wrote with "
                         "--record-dir") from None
    if not isinstance(manifest, dict) or not isinstance(manifest.get("arrays"), str):
        raise ValueError(f"episode manifest {manifest_path} is not one a bridge wrote (no 'arrays' file named); pass "
                         "the .json a bridge wrote with --record-dir")
    arrays: dict[str, np.ndarray] = {}
    with h5py.File(manifest_path.parent / manifest["arrays"], "r") as f:
        f.visititems(lambda name, obj: arrays.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return manifest, arrays
