"""One service, several tasks (``jepa-monitor tasks-study``): each task calibrated on its own held-out labelled
rollouts through the public HTTP API, its live rollouts alerted on by the service, beside what one threshold
pooled over the tasks would do to each.

For each task's records file (``jepa-policy eval --keep-latents --out``, or a pick job's ``decisions.jsonl.gz``):
1. a real server (uvicorn, a SQLite file) registers the task with its latent size; ``replay`` sends the file's
   first ``held_out_share`` of episodes as held-out labelled rollouts and the rest live, as a robot sends them;
2. ``POST /v1/calibrations`` calibrates the task on its held-out episodes (the alert rule at ``alpha``);
3. the live episodes are scored and alerted on by the service as they arrive; ``GET /v1/alerts`` and
   ``GET /v1/episodes/{id}`` read what it decided and the NMSE it scored;
4. the pooled threshold: the same rule calibrated once on every task's held-out successes together (the service
   cannot pool them itself: a task has one latent size), each task's live episodes judged by it offline with the
   service's own rule code. The per-task rule is judged offline the same way, a check that it agrees with the
   service's live alerts.
Per task: the threshold, the promised length bins, the false-alert rate on live successes and the detection of
live failures (by failure kind where the records name them), under its own threshold and under the pooled one;
the distribution of each episode's largest running-median NMSE, successes and failures side by side.
"""
from __future__ import annotations

import secrets
import tempfile
from pathlib import Path

import httpx
import numpy as np

from monitor_service import rules
from monitor_service.offline.figures import pyplot
from monitor_service.offline.replay import read_records, replay
from monitor_service.server import start_server

def _rate(k: int, n: int) -> dict:
    return {"k": k, "n": n, "rate": k / n if n else None, "ci": rules.binomial_ci(k, n)}


def _scores(http: httpx.Client, headers: dict, episode_id: str, success: bool, length: int | None
            ) -> rules.EpisodeScores:
    detail = http.get(f"/v1/episodes/{episode_id}", headers=headers)
    detail.raise_for_status()
    return rules.EpisodeScores.from_decisions(detail.json()["decisions"], success, length, episode=episode_id)


def _judged(rule: rules.CalibratedRule, episodes: list[rules.EpisodeScores], kinds: dict[str, str]) -> dict:
    """False alerts on successes and detection of failures (overall and per failure kind) under ``rule``."""
    verdicts = {e.episode: rule.judge(e) for e in episodes}
    succ = [e for e in episodes if e.success]
    fail = [e for e in episodes if not e.success]
    by_kind = {}
    for kind in sorted({kinds.get(e.episode, "failure") for e in fail}):
        members = [e for e in fail if kinds.get(e.episode, "failure") == kind]
        by_kind[kind] = _rate(sum(verdicts[e.episode]["alerted"] for e in members), len(members))
    return {"false_alerts": _rate(sum(verdicts[e.episode]["alerted"] for e in succ), len(succ)),
            "detection": _rate(sum(verdicts[e.episode]["alerted"] for e in fail), len(fail)),
            "detection_by_kind": by_kind,
            "alerted": sorted(e.episode for e in episodes if verdicts[e.episode]["alerted"])}


def peak_running_nmse(episode: rules.EpisodeScores, window: int) -> float | None:
    r = rules.running_statistic(episode.nmse, window)
    return float(r.max()) if r.size else None


def run_tasks_study(files: dict[str, str | Path], where: dict[str, str] | None = None, held_out_share: float = 0.5,
                    alpha: float = 0.1, rule: str = "running", work_dir: str | Path | None = None,
                    progress: bool = False, in_flight: int = 0) -> dict:
    """The study of the module docstring; returns its figures (JSON-ready but for ``_peaks``, each task's peak
    values for the figure). ``progress``: bars of the episodes replayed on stderr. ``work_dir``: keep the
    service's database (``tasks_study.db``) and log there. ``in_flight``: each task's last that many live
    episodes are sent without their outcome (judged all the same, from their records): a dashboard served on
    the kept database shows them running."""
    if not 0 < held_out_share < 1:
        raise ValueError(f"held_out_share must lie in (0, 1), got {held_out_share}")
    loaded = {task: read_records(path, where) for task, path in files.items()}
    for task, rows in loaded.items():
        if not rows:
            raise ValueError(f"{files[task]}: no episode records for {task}" + (f" with {where}" if where else ""))
    tmp = tempfile.TemporaryDirectory() if work_dir is None else None
    base = Path(tmp.name if tmp else work_dir)
    if (base / "tasks_study.db").exists():
        raise ValueError(f"{base / 'tasks_study.db'} exists already (an earlier study's): keep this one in another "
                         "folder, or remove that file")
    base.mkdir(parents=True, exist_ok=True)
    out: dict = {"alpha": alpha, "rule": rule, "held_out_share": held_out_share, "tasks": {}}
    admin = {"X-API-Key": secrets.token_urlsafe(24)}   # a kept database must not open to a key anyone can read
    try:
        with start_server(f"sqlite:///{base / 'tasks_study.db'}", admin_key=admin["X-API-Key"],
                          log_path=base / "server.log") as server, \
                httpx.Client(base_url=server.url, timeout=120) as http:
            robot_key = http.post("/v1/keys", headers=admin, json={"name": "replay", "role": "robot",
                                                                   "robot": "replay"}).json()["key"]
            held, live, kinds, service_alerts = {}, {}, {}, {}
            for task, rows in loaded.items():
                dim = len(next(d["z_hat"] for r in rows for d in r["decisions"] if "z_hat" in d))
                put = http.put(f"/v1/tasks/{task}", json={"latent_dim": dim}, headers=admin)
                if put.status_code >= 300:
                    raise ValueError(f"task {task!r}: the service refused it: {put.json().get('detail')}")
                n_held = round(held_out_share * len(rows))
                sent = replay(rows[:n_held], server.url, robot_key, task, n_held, prefix=f"{task}-cal-",
                              robot="replay", progress=progress)
                cal = http.post("/v1/calibrations", headers=admin,
                                json={"task": task, "alpha": alpha, "rule": rule, "n_bootstrap": 500,
                                      "n_permutation": 500})
                if cal.status_code != 201:
                    raise ValueError(f"{task}: the service refused its calibration: {cal.json().get('detail')}")
                result = cal.json()["result"]
                live_sent = replay(rows[n_held:], server.url, robot_key, task, 0, prefix=f"{task}-live-",
                                   robot="replay", progress=progress, in_flight=in_flight)
                for what in (sent, live_sent):
                    if what.rejected or what.dropped:
                        raise ValueError(f"{task}: the service refused {len(what.rejected)} and dropped "
                                         f"{what.dropped} of its records, e.g. {(what.rejected or ['-'])[0]}")
                held[task] = [_scores(http, admin, eid, bool(r["success"]), r.get("length"))
                              for eid, r in zip(sent.episode_ids, rows[:n_held])]
                live[task] = [_scores(http, admin, eid, bool(r["success"]), r.get("length"))
                              for eid, r in zip(live_sent.episode_ids, rows[n_held:])]
                out["tasks"][task] = {"held_out_successes": sum(e.success for e in held[task]),
                                      "held_out_failures": sum(not e.success for e in held[task])}
                kinds.update({eid: str(r.get("failure_kind") or "failure")
                              for eid, r in zip(live_sent.episode_ids, rows[n_held:]) if not r["success"]})
                alerts = http.get("/v1/alerts", params={"task": task, "limit": 5000}, headers=admin).json()
                service_alerts[task] = sorted({a["episode_id"] for a in alerts})
                out["tasks"][task] |= {"file": str(files[task]), "latent_dim": dim, "episodes": len(rows),
                                      "held_out": n_held, "calibration": {
                                          "n_success": result["n_success"], "n_failure": result["n_failure"],
                                          "auroc": result["auroc"], "auroc_ci": [result["auroc_ci_low"],
                                                                                 result["auroc_ci_high"]],
                                          "threshold": cal.json()["threshold"], "note": result["rule"]["note"],
                                          "regimes": result["rule"]["regimes"]},
                                      "rule": result["rule"]}
            if tmp is None:   # kept: its own keys die with the study (`jepa-monitor keys create` makes yours)
                keys = http.get("/v1/keys", headers=admin).json()
                for key in sorted(keys, key=lambda k: k["role"] == "admin"):
                    http.delete(f"/v1/keys/{key['id']}", headers=admin).raise_for_status()
        params = rules.RuleParams(rule)
        pooled = rules.calibrate_rule([e for task in held for e in held[task] if e.success], params, alpha)
        out["pooled"] = {"threshold": pooled.threshold, "note": pooled.note,
                         "successes": pooled.n_successes}
        for task, episodes in live.items():
            own = rules.CalibratedRule.from_dict(out["tasks"][task].pop("rule"))
            mine, theirs = _judged(own, episodes, kinds), _judged(pooled, episodes, kinds)
            service = {"alerted": service_alerts[task],
                       "agrees_with_offline": service_alerts[task] == mine["alerted"]}
            peaks = {label: [p for e in episodes if e.success is want
                             for p in [peak_running_nmse(e, params.window)] if p is not None]
                     for label, want in (("successes", True), ("failures", False))}
            out["tasks"][task].update(
                live={"successes": sum(e.success for e in episodes), "failures": sum(not e.success for e in episodes)},
                own_threshold={k: v for k, v in mine.items() if k != "alerted"},
                pooled_threshold={k: v for k, v in theirs.items() if k != "alerted"},
                service={"alerted_episodes": len(service["alerted"]), "agrees_with_offline":
                         service["agrees_with_offline"]},
                peak_running_nmse={label: (np.percentile(v, [10, 50, 90]).tolist() if v else None)
                                   for label, v in peaks.items()},
                _peaks=peaks)
    finally:
        if tmp is not None:
            tmp.cleanup()
    return out


def _quantiles(v: list[float] | None) -> str:
    return "-" if v is None else " / ".join(f"{x:.3g}" for x in v)


def tasks_table(study: dict) -> str:
    """Markdown: per task, its threshold and what it and the pooled threshold do to its live episodes."""
    def pct(r: dict) -> str:
        return "-" if not r["n"] else f"{r['k']}/{r['n']} = {r['rate']:.2f} [{r['ci'][0]:.2f}, {r['ci'][1]:.2f}]"

    lines = [f"Alert rule `{study['rule']}` at alpha {study['alpha']}; pooled threshold "
             f"{study['pooled']['threshold']:.4g} ({study['pooled']['successes']} held-out successes of every "
             "task together).", "",
             "| task | held out (s/f) | its threshold | promised bins | false alerts, own | false alerts, pooled "
             "| detection, own | detection, pooled | service = offline |",
             "|---|---|---|---|---|---|---|---|---|"]
    for task, t in study["tasks"].items():
        cal = t["calibration"]
        promised = ", ".join(f"{r['lo']}-{r['hi']}" + ("" if r.get("promise", True) else f" (none: {r['n']})")
                             for r in cal["regimes"])
        lines.append(f"| {task} | {t['held_out_successes']}/{t['held_out_failures']} | {cal['threshold']:.4g} | "
                     f"{promised} | "
                     f"{pct(t['own_threshold']['false_alerts'])} | {pct(t['pooled_threshold']['false_alerts'])} | "
                     f"{pct(t['own_threshold']['detection'])} | {pct(t['pooled_threshold']['detection'])} | "
                     f"{'yes' if t['service']['agrees_with_offline'] else 'NO'} |")
    lines += ["", "| task | failure kind | detection, own | detection, pooled |", "|---|---|---|---|"]
    for task, t in study["tasks"].items():
        for kind, r in t["own_threshold"]["detection_by_kind"].items():
            lines.append(f"| {task} | {kind} | {pct(r)} | {pct(t['pooled_threshold']['detection_by_kind'][kind])} |")
    lines += ["", "| task | peak running-median NMSE of successes (p10 / p50 / p90) | of failures |", "|---|---|---|"]
    for task, t in study["tasks"].items():
        q = t["peak_running_nmse"]
        lines.append(f"| {task} | {_quantiles(q['successes'])} | {_quantiles(q['failures'])} |")
    return "\n".join(lines)


def tasks_figure(study: dict, path: str | Path) -> Path:
    """One panel per task: each live episode's peak running-median NMSE (successes, failures) against the
    task's own threshold and the pooled one."""
    plt = pyplot()
    tasks = list(study["tasks"])
    fig, axes = plt.subplots(1, len(tasks), figsize=(4.4 * len(tasks), 3.6), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        t = study["tasks"][task]
        values = [v for vs in t["_peaks"].values() for v in vs]
        bins = np.logspace(np.log10(min(values)), np.log10(max(values)), 25) if values else 10
        for label, color in (("successes", "tab:green"), ("failures", "tab:red")):
            ax.hist(t["_peaks"][label], bins=bins, alpha=0.55, color=color, label=label)
        if study["rule"] == "running":   # a band rule's threshold is on z-scores of log NMSE, not on this axis
            ax.axvline(t["calibration"]["threshold"], color="black", label="its threshold")
            ax.axvline(study["pooled"]["threshold"], color="black", linestyle="--", label="pooled threshold")
        ax.set(xscale="log", title=task, xlabel="peak running-median NMSE of a live episode", ylabel="episodes")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
