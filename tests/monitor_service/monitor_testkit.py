"""Shared helpers of the monitor tests: settings in a temp dir, keys, and synthetic episodes."""
from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np

from monitor_service.scoring import nmse
from monitor_service.settings import MonitorSettings

ADMIN = "test-admin-key"
DIM = 16


def make_settings(tmp_path, **overrides) -> MonitorSettings:
    values = dict(database_url=f"sqlite:///{tmp_path / 'monitor.db'}", admin_key=ADMIN, n_bootstrap=500,
                  n_permutation=500, create_database=True)
    values.update(overrides)
    return MonitorSettings(**values)


def new_key(client, name, role, robot=None) -> dict:
    r = client.post("/v1/keys", json={"name": name, "role": role, "robot": robot}, headers={"X-API-Key": ADMIN})
    assert r.status_code == 201, r.text
    return {"X-API-Key": r.json()["key"]}


def episode_records(episode, task, rng, noise, n_steps=8, horizon=1, dim=DIM, held_out=True, success=None, group=None):
    """Records of one episode in send order: decision t, then the realized latent of step t + horizon.

    The prediction error relative to the target's RMS is ``noise``, so the per-decision NMSE is about noise^2.
    Returns (records, list of (z_hat, z) per decision for reference scoring).
    """
    recs, pairs = [], []
    for t in range(n_steps):
        z = rng.normal(size=dim) * rng.uniform(0.5, 2.0)
        z_hat = z + noise * np.sqrt(np.mean(z * z)) * rng.normal(size=dim)
        dec = {"kind": "decision", "task": task, "episode": episode, "step": t, "horizon": horizon,
               "z_hat": z_hat.astype(np.float32).tolist(), "held_out": held_out}
        if group is not None:
            dec["group"] = group
        recs.append(dec)
        recs.append({"kind": "target", "episode": episode, "step": t + horizon, "z": z.astype(np.float32).tolist()})
        pairs.append((np.float32(z_hat), np.float32(z)))
    if success is not None:
        recs.append({"kind": "outcome", "episode": episode, "success": success})
    return recs, pairs


def register_task(client, name, dim=DIM):
    r = client.put(f"/v1/tasks/{name}", json={"latent_dim": dim}, headers={"X-API-Key": ADMIN})
    assert r.status_code == 200, r.text


def post_batch(client, headers, records, key=None):
    h = dict(headers)
    if key:
        h["Idempotency-Key"] = key
    return client.post("/v1/batch", json={"records": records}, headers=h)


def records_for_nmse(episode, task, rng, nmse_values, steps=None, horizon=4, dim=DIM, held_out=True, success=None,
                     length=None, persistence=None):
    """Records of one episode whose decision t has (up to float32 rounding) the given NMSE: z_hat is the target
    moved by rms(z) * sqrt(nmse * dim) along a random unit direction. ``persistence``: NMSE values of a z_now
    sent with each decision (the persistence control), built the same way."""
    steps = list(range(0, 8 * len(nmse_values), 8)) if steps is None else list(steps)
    recs = []

    def moved(z, value):
        direction = rng.normal(size=dim)
        direction /= np.linalg.norm(direction)
        return (z + direction * np.sqrt(np.mean(z * z)) * np.sqrt(value * dim)).astype(np.float32).tolist()

    for i, (t, value) in enumerate(zip(steps, nmse_values)):
        z = rng.normal(size=dim)
        dec = {"kind": "decision", "task": task, "episode": episode, "step": t, "horizon": horizon,
               "z_hat": moved(z, value), "held_out": held_out}
        if persistence is not None:
            dec["z_now"] = moved(z, persistence[i])
        recs += [dec, {"kind": "target", "episode": episode, "step": t + horizon, "z": z.astype(np.float32).tolist()}]
    if success is not None:
        out = {"kind": "outcome", "episode": episode, "success": success}
        if length is not None:
            out["length"] = length
        recs.append(out)
    return recs


def _stat(pid) -> list[str] | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None


def children(pid: int) -> list[int]:
    """Pids whose parent is ``pid``."""
    return [int(p.name) for p in Path("/proc").iterdir()
            if p.name.isdigit() and (st := _stat(p.name)) is not None and int(st[1]) == pid]


def alive(pid: int) -> bool:
    """Running and not a zombie (a zombie only waits for init to reap it)."""
    st = _stat(pid)
    return st is not None and st[0] != "Z"


def records_with_scores(episode, task, rng, nmse_values, scores: dict, steps=None, held_out=True, success=None,
                        length=None):
    """``records_for_nmse`` whose decisions also carry named scores ({name: per-decision values}, NaN: left
    out of that decision); with ``nmse_values`` None the decisions send scores only (no latents)."""
    n = len(next(iter(scores.values())))
    steps = list(range(0, 8 * n, 8)) if steps is None else list(steps)
    if nmse_values is None:
        recs = [{"kind": "decision", "task": task, "episode": episode, "step": t, "held_out": held_out}
                for t in steps]
    else:
        recs = records_for_nmse(episode, task, rng, nmse_values, steps, held_out=held_out)
    decisions = [r for r in recs if r["kind"] == "decision"]
    for i, dec in enumerate(decisions):
        present = {name: float(v[i]) for name, v in scores.items() if np.isfinite(v[i])}
        if present:
            dec["scores"] = present
    recs = [r for r in recs if r["kind"] != "decision" or "z_hat" in r or "scores" in r]
    if success is not None:
        out = {"kind": "outcome", "episode": episode, "success": success}
        if length is not None:
            out["length"] = length
        recs.append(out)
    return recs


def latent_records(n_success: int, n_failure: int, seed: int, dim: int = 16,
                   noise: tuple[float, float] = (0.3, 0.9)) -> list[dict]:
    """Recorded episodes (nothing sent yet) as `jepa-policy eval --keep-latents --out` writes them: failures
    predict their future worse; a last decision's target never comes (the episode ended first)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_success + n_failure):
        fail = i % (n_success + n_failure) >= n_success
        length = int(rng.integers(30, 80))
        decisions = []
        for step in range(0, length, 8):
            z_now, z_real = rng.normal(size=dim), rng.normal(size=dim)
            z_hat = z_real + noise[fail] * rng.normal(size=dim)
            d = {"step": step, "target_step": step + 4, "z_hat": z_hat.tolist(), "z_now": z_now.tolist(),
                 "scores": {"stac": float(rng.uniform())}}
            if step + 4 <= length:
                d.update(z_real=z_real.tolist(), nmse=nmse(z_hat, z_real))
            decisions.append(d)
        out.append({"episode": i, "seed": 1000 * seed + i, "success": not fail, "length": length,
                    "decisions": decisions, "arm": "jepa"})
        if fail:
            out[-1]["failure_kind"] = ("never_grasped", "dropped")[i % 2]
    order = np.random.default_rng(seed + 1).permutation(len(out))
    return [out[i] for i in order]


def write_records(path, rows):
    with gzip.open(path, "wt") as f:
        for row in rows:
            f.write(json.dumps(row) + "\n")
    return path
