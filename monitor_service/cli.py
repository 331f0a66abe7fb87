"""``jepa-monitor``: serve, db, keys, tasks, calibrate, study, compare, ceiling, report, replay, tasks-study,
bench."""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from monitor_service.offline import compare_cli


def _settings(args, database: str | None = None):
    """The settings; ``database``: "existing" (refused when missing) or "create" (made when missing) checks the
    database URL first, with a one-line error naming the fix."""
    from monitor_service import db
    from monitor_service.settings import MonitorSettings

    overrides = {}
    url = getattr(args, "database_url", None)
    if url is not None and not url.strip():
        raise ValueError("--database-url is empty; give sqlite:///jepa_monitor.db, sqlite:////absolute/path.db or "
                         "postgresql+psycopg://user@host/db, or leave the option out (JEPA_MONITOR_DATABASE_URL)")
    if url:
        overrides["database_url"] = url
    settings = MonitorSettings(**overrides)
    if database is not None:
        db.check_database_url(settings.database_url, create=database == "create")
    return settings


def _share(text: str) -> float:
    """A share in (0, 1), for argparse."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a share between 0 and 1, e.g. 0.75, got {text!r}") from None
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a share strictly between 0 and 1, e.g. 0.75, got {value}")
    return value


def _sessionmaker(args):
    from monitor_service import db

    settings = _settings(args, "existing")
    engine = db.make_engine(settings.database_url)
    db.upgrade(engine)
    return settings, db.make_sessionmaker(engine)


def cmd_serve(args) -> int:
    import uvicorn

    from monitor_service import db

    settings = _settings(args, "create" if args.create else "existing")
    if args.database_url:
        os.environ["JEPA_MONITOR_DATABASE_URL"] = args.database_url
    db.upgrade(db.make_engine(settings.database_url))  # once, before any worker starts (it creates the file)
    if args.workers > 1:   # each worker exits when this supervising process dies (app.exit_with_parent)
        os.environ["JEPA_MONITOR_SUPERVISOR_PID"] = str(os.getpid())
    if args.workers > 1 and not os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        os.environ["PROMETHEUS_MULTIPROC_DIR"] = tempfile.mkdtemp(prefix="jepa-monitor-prom-")
    if os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        # Workers write their samples here; stale files of an earlier run would be summed in, so start empty.
        prom_dir = os.environ["PROMETHEUS_MULTIPROC_DIR"]
        os.makedirs(prom_dir, exist_ok=True)
        for name in os.listdir(prom_dir):
            if name.endswith(".db"):
                os.remove(os.path.join(prom_dir, name))
    uvicorn.run(
        "monitor_service.app:create_app", factory=True, host=args.host, port=args.port, workers=args.workers,
        log_level=args.log_level, timeout_graceful_shutdown=5,
    )
    return 0


def cmd_db(args) -> int:
    from monitor_service import db

    url = _settings(args, "create" if args.action in ("upgrade", "restore") else "existing").database_url
    if args.action in ("backup", "restore"):
        if not args.path:
            raise SystemExit(f"db {args.action} needs a file: jepa-monitor db {args.action} FILE")
        (db.backup_sqlite if args.action == "backup" else db.restore_sqlite)(url, args.path)
        print(f"{'backed up to' if args.action == 'backup' else 'restored from'} {args.path}")
    engine = db.make_engine(url)
    if args.action == "upgrade":
        db.upgrade(engine)
    elif args.action == "prune":
        n = db.prune_idempotency_keys(engine, args.older_than_days)
        print(f"removed {n} idempotency keys older than {args.older_than_days} days")
    print(f"revision {db.current_revision(engine)} (head {db.head_revision()})")
    return 0


def cmd_keys(args) -> int:
    from sqlalchemy import select

    from monitor_service.auth import create_key, revoke
    from monitor_service.db import ApiKey

    _, make_session = _sessionmaker(args)
    with make_session() as session:
        if args.action == "create":
            row, secret = create_key(session, args.name, args.role, args.robot)
            session.commit()
            print(json.dumps({"id": row.id, "name": row.name, "role": row.role, "robot": row.robot, "key": secret}))
        elif args.action == "list":
            for k in session.scalars(select(ApiKey).order_by(ApiKey.id)):
                print(f"{k.id}\t{k.name}\t{k.role}\t{k.robot or '-'}\t{'revoked' if k.revoked_at else 'active'}")
        else:
            try:
                revoke(session, args.id)
            except LookupError as exc:
                raise LookupError(f"{exc}; list them with `jepa-monitor keys list`") from None
            session.commit()
            print(f"revoked key {args.id}")
    return 0


def cmd_tasks(args) -> int:
    from sqlalchemy import select

    from monitor_service.db import Task
    from monitor_service.schemas import RESERVED_SIGNALS

    _, make_session = _sessionmaker(args)
    with make_session() as session:
        if args.action == "add":
            signals = sorted({s.strip() for s in (args.signals or "").split(",") if s.strip()})
            own = [s for s in signals if s in RESERVED_SIGNALS]
            if own:
                raise ValueError(f"{own[0]} is the service's own signal (computed from the latents); --signals names "
                                 "the scores robots send")
            clash = [(name, t.latent_dim) for name in args.names if (t := session.get(Task, name)) is not None
                     and args.latent_dim is not None and t.latent_dim != args.latent_dim]
            if clash:   # checked before anything is added: the command changes all of its tasks or none
                name, dim = clash[0]
                raise ValueError(f"task {name} exists with latent_dim {dim}, not {args.latent_dim}: its records and "
                                 f"calibrations are {dim}-d; register the new model's task under another name (e.g. "
                                 f"{name}-{args.latent_dim}), or drop --latent-dim to add only signals")
            for name in args.names:
                task = session.get(Task, name)
                if task is None:
                    session.add(Task(name=name, latent_dim=args.latent_dim, description="", signals=signals))
                elif signals:
                    task.signals = sorted(set(task.signals or []) | set(signals))
            session.commit()
        for t in session.scalars(select(Task).order_by(Task.name)):
            print(f"{t.name}\tlatent_dim={t.latent_dim}\tsignals={','.join(t.signals or []) or '-'}")
    return 0


def cmd_calibrate(args) -> int:
    from monitor_service.service import calibrate_task
    from monitor_service.offline.study import study_table

    settings, make_session = _sessionmaker(args)
    row = calibrate_task(
        make_session, settings, args.task, args.checkpoint, args.alpha, args.rule, args.n_bootstrap,
        args.n_permutation, args.seed, args.folds, args.shape,
        [s.strip() for s in args.signals.split(",")] if args.signals else None, args.combination,
    )
    r = row.result
    print(f"calibration #{row.id} task={row.task} checkpoint={row.checkpoint or '-'} "
          f"(n_success={r['n_success']}, n_failure={r['n_failure']}, skipped={r['skipped_episodes']})")
    print(f"  early score: AUROC {r['auroc']:.3f} [95% CI {r['auroc_ci_low']:.3f}, {r['auroc_ci_high']:.3f}]  "
          f"PR-AUC {r['average_precision']:.3f}  permutation p {r['permutation_p']:.4f}")
    held = "n/a" if r["youden_bacc_held_out"] is None else f"{r['youden_bacc_held_out']:.3f}"
    print(f"  Youden threshold {r['youden_threshold']:.4g}: balanced accuracy in-sample "
          f"{r['youden_bacc_in_sample']:.3f}, held-out {held} ({r['held_out_method']})")
    rule = r["rule"]
    print(f"  alert rule {row.rule} (window {rule['params']['window']}, debounce {rule['params']['debounce']}): "
          f"threshold {row.threshold:.4g} at alpha={r['alpha']} ({rule['note']})")
    spec = r["detector"]["spec"]
    print(f"  detector {spec['combination']} of {', '.join(spec['signals'])}: {r['detector']['note']}")
    for name, figures in r.get("signals", {}).items():   # each signal with data, e.g. nmse beside nmse_ratio
        a = figures.get("early_auroc") or {}
        auc = "n/a" if a.get("auroc") is None else \
            f"{a['auroc']:.3f} [{a['ci'][0]:.3f}, {a['ci'][1]:.3f}] over {a['n']} episodes"
        print(f"  signal {name}: early-score AUROC {auc}")
    print(study_table(r["detection"]))
    for name, c in r["controls"].items():
        value = "n/a: " + c["reason"] if c["auroc"] is None else \
            f"AUROC {c['auroc']:.3f} [{c['ci'][0]:.3f}, {c['ci'][1]:.3f}] over {c['n']} episodes"
        print(f"  control {name}: {value}")
    return 0


def cmd_report(args) -> int:
    from monitor_service.service import report

    _, make_session = _sessionmaker(args)
    with make_session() as session:
        rep = report(session)
        rows = [
            {"task": r.task, "checkpoint": r.checkpoint, "auroc": r.auroc,
             "ci": [r.result["auroc_ci_low"], r.result["auroc_ci_high"]],
             "pr_auc": r.result["average_precision"], "p": r.result["permutation_p"], "threshold": r.threshold,
             "rule": r.rule, "n_success": r.result["n_success"], "n_failure": r.result["n_failure"]}
            for r in rep["tasks"]
        ]
    if args.json:
        print(json.dumps({"tasks": rows, "uncalibrated_tasks": rep["uncalibrated_tasks"], "pooled": rep["pooled"]},
                         indent=2))
        return 0
    print(f"{'task':<20}{'ckpt':<12}{'AUROC':>7}  {'95% CI':<15}{'PR-AUC':>7}{'perm p':>9}{'threshold':>11}  n(s/f)")
    for r in rows:
        thr = "inf" if r["threshold"] is None else f"{r['threshold']:.4g}"
        print(f"{r['task']:<20}{(r['checkpoint'] or '-'):<12}{r['auroc']:>7.3f}  [{r['ci'][0]:.3f}, {r['ci'][1]:.3f}] "
              f"{r['pr_auc']:>7.3f}{r['p']:>9.4f}{thr:>11}  {r['n_success']}/{r['n_failure']}")
    if rep["uncalibrated_tasks"]:
        print("uncalibrated (no alerts):", ", ".join(rep["uncalibrated_tasks"]))
    pooled = rep["pooled"]
    if pooled["auroc"] is not None:
        print(f"\npooled AUROC {pooled['auroc']:.3f} over {pooled['n_episodes']} episodes -- {pooled['warning']}")
    return 0


def cmd_study(args) -> int:
    from monitor_service.rules import RuleParams
    from monitor_service.offline.study import (length_check, length_table, load_episodes, run_study, study_table,
                                       synthetic_study)

    settings = _settings(args)
    params = RuleParams("running", args.window or settings.running_window, args.debounce or settings.alert_debounce,
                        settings.alert_clear_ratio, args.shape or settings.threshold_shape)
    alpha = args.alpha or settings.alpha
    if args.length_check:
        if args.records or args.synthetic:
            raise ValueError("--length-check runs on its own synthetic episodes; drop the records file / --synthetic")
        check = length_check(args.draws, args.fresh, args.successes, params=params, seed=args.seed,
                             alphas=(args.alpha,) if args.alpha else (0.05, 0.2), progress=not args.no_progress,
                             short_share=args.short_share, promise_min=args.promise_min)
        print(json.dumps(check, indent=2) if args.json else length_table(check))
        return 0
    if args.synthetic:
        if args.records:
            raise ValueError("give either a records file or --synthetic N, not both")
        n_success, n_failure = (int(x) for x in args.episodes.split(","))
        result = synthetic_study(args.synthetic, n_success, n_failure, params, alpha, args.folds, args.seed)
        source = f"synthetic task, {args.synthetic} decisions per episode (monitor_service/offline/synthetic.py)"
    else:
        if not args.records:
            raise ValueError("give a records file (JSONL) or --synthetic N")
        where = _where(args.where)
        episodes, skipped = load_episodes(args.records, where)
        if not episodes:
            raise ValueError(f"{args.records} holds no labelled episode with a scored decision ({skipped})")
        result = run_study(episodes, params, alpha, args.folds, args.seed)
        result["skipped"] = skipped
        source = args.records
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    r = result["early_score_auroc"]
    ranking = "n/a" if r["auroc"] is None else f"{r['auroc']:.3f} [{r['ci'][0]:.3f}, {r['ci'][1]:.3f}]"
    print(f"{source}: {result['episodes']} episodes ({result['successes']} successes, {result['failures']} "
          f"failures), median {result['scored_decisions_per_episode']['median']:g} scored decisions per episode; "
          f"early-score AUROC {ranking}")
    print(study_table(result["rules"]))
    return 0


def cmd_bench(args) -> int:
    from monitor_service.bench import run_bench

    results = run_bench(dim=args.dim, seconds=args.seconds, concurrency=args.concurrency, batch=args.batch,
                        batch_concurrency=args.batch_concurrency, host=args.host, port=args.port,
                        admin_key=args.admin_key, database_url=args.database_url, servers=args.servers,
                        workers=args.workers, client_decisions=args.client_decisions, floor=not args.no_floor,
                        rounds=args.rounds, progress=not args.no_progress, out=sys.stderr if args.json else sys.stdout)
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=2))
    if args.json:
        print(json.dumps(results, indent=2))
    return 0


def _where(items: list[str] | None) -> dict[str, str]:
    """``--where FIELD=VALUE`` options as a dict; ValueError naming a malformed one."""
    out = {}
    for item in items or []:
        field, sep, value = item.partition("=")
        if not sep or not field:
            raise ValueError(f"--where {item!r}: give FIELD=VALUE, e.g. --where arm=jepa")
        out[field] = value
    return out


def _held_out(text: str) -> float:
    """``--held-out``: a count of episodes (N) or a share of them (0 < P < 1), for argparse."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a count (e.g. 100) or a share (e.g. 0.5), got {text!r}") from None
    if value < 0 or (value >= 1 and value != int(value)):
        raise argparse.ArgumentTypeError(f"expected a count >= 0 or a share between 0 and 1, got {text}")
    return value


def cmd_replay(args) -> int:
    from monitor_service.offline.replay import read_records, replay

    where = _where(args.where)
    records = read_records(args.records, where)
    if not records:
        raise ValueError(f"{args.records}: no episode records" + (f" with {where}" if where else ""))
    key = args.api_key or os.environ.get("JEPA_POLICY_MONITOR_KEY")
    if not key:
        raise ValueError("give the robot key the records are sent with: --api-key KEY or JEPA_POLICY_MONITOR_KEY "
                         "(`jepa-monitor keys create --name NAME --role robot --robot ROBOT`)")
    held = round(args.held_out * len(records)) if 0 < args.held_out < 1 else int(args.held_out)
    signals = tuple(x for x in (args.signals or "").split(",") if x)
    summary = replay(records, args.url, key, args.task, held, robot=args.robot, prefix=args.prefix,
                     checkpoint=args.checkpoint, group=args.group, signals=signals, progress=not args.no_progress,
                     part=args.part, in_flight=args.in_flight)
    out = summary.to_dict()
    if args.json:
        print(json.dumps(out))
    else:
        print(f"{args.task}: {out['episodes']} episodes ({out['held_out']} held out for calibration, "
              f"{out['episodes'] - out['held_out']} live"
              + (f", the last {out['in_flight']} still running" if out["in_flight"] else "")
              + f"), {out['decisions']} decisions, {out['targets']} realized "
              f"latents sent to {args.url}; {len(out['rejected'])} refused, {out['dropped']} dropped")
        for line in out["rejected"][:10]:
            print(f"  refused: {line}")
    return 1 if out["rejected"] or out["dropped"] else 0


def cmd_tasks_study(args) -> int:
    from monitor_service.offline.tasks import run_tasks_study, tasks_figure, tasks_table

    files = {}
    for item in args.task:
        task, sep, path = item.partition("=")
        if not sep or not task or not path:
            raise ValueError(f"--task {item!r}: give TASK=RECORDS, e.g. --task Lift=demo_out/Lift/decisions.jsonl.gz")
        files[task] = path
    compare_cli.check_out(args.out, (".json", ".md", ".png"))
    study = run_tasks_study(files, _where(args.where), args.held_out, args.alpha, args.rule, work_dir=args.keep,
                            progress=not args.no_progress, in_flight=args.in_flight)
    table = tasks_table(study)
    figures = [tasks_figure(study, path) for path in args.out if path.endswith(".png")]
    for t in study["tasks"].values():
        t.pop("_peaks", None)
    for path in args.out:
        if path.endswith(".json"):
            Path(path).write_text(json.dumps(study, indent=2))
        elif path.endswith(".md"):
            Path(path).write_text(table + "".join(f"\n\n![peak running-median NMSE per task]({p.name})"
                                                  for p in figures) + "\n")
    print(json.dumps(study, indent=2) if args.json else table)
    return 0


def _version() -> str:
    """This install's version, for --version."""
    try:
        return version("jepa-policy-toolkit")
    except PackageNotFoundError:
        return "unknown (not installed: pip install -e . in the checkout)"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jepa-monitor", description=__doc__)
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    p.add_argument("--database-url", help="overrides JEPA_MONITOR_DATABASE_URL")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("serve", help="run the HTTP service with uvicorn")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8765)
    s.add_argument("--workers", type=int, default=1)
    s.add_argument("--log-level", default="info")
    s.add_argument("--create", action="store_true",
                   help="create the SQLite database if it does not exist (else only `db upgrade` creates one)")
    s.set_defaults(func=cmd_serve)

    s = sub.add_parser("db", help="schema migrations (upgrade, current), housekeeping (prune), backup, restore")
    s.add_argument("action", choices=["upgrade", "current", "prune", "backup", "restore"])
    s.add_argument("path", nargs="?", help="backup / restore: the backup file (SQLite)")
    s.add_argument("--older-than-days", type=float, default=7.0, help="prune: idempotency keys older than this")
    s.set_defaults(func=cmd_db)

    s = sub.add_parser("keys", help="API keys")
    ks = s.add_subparsers(dest="action", required=True)
    c = ks.add_parser("create")
    c.add_argument("--name", required=True)
    c.add_argument("--role", required=True, choices=["robot", "operator", "admin"])
    c.add_argument("--robot", help="required for robot keys")
    ks.add_parser("list")
    r = ks.add_parser("revoke")
    r.add_argument("id", type=int)
    s.set_defaults(func=cmd_keys)

    s = sub.add_parser("tasks", help="register or list tasks")
    ts = s.add_subparsers(dest="action", required=True)
    a = ts.add_parser("add")
    a.add_argument("names", nargs="+")
    a.add_argument("--latent-dim", type=int)
    a.add_argument("--signals", help="comma-separated names of per-decision scores robots may send, e.g. stac,rnd")
    ts.add_parser("list")
    s.set_defaults(func=cmd_tasks)

    s = sub.add_parser("calibrate", help="calibrate one task from its stored held-out episodes")
    s.add_argument("--task", required=True, help="registered task name")
    s.add_argument("--checkpoint", help="calibrate only this checkpoint's episodes")
    s.add_argument("--alpha", type=float, help="guaranteed false-alert rate per successful episode (default 0.1)")
    s.add_argument("--rule", choices=["running", "band"], help="alert rule (default: JEPA_MONITOR_ALERT_RULE)")
    s.add_argument("--shape", choices=["flat", "running-max"],
                   help="threshold shape over the decision index (default: JEPA_MONITOR_THRESHOLD_SHAPE)")
    s.add_argument("--signals", help="comma-separated signals that alert (default nmse), e.g. stac, nmse,stac or "
                   "nmse_ratio (NMSE over the persistence NMSE: needs z_now with each decision)")
    s.add_argument("--combination", choices=["single", "fiper", "bonferroni"],
                   help="how several signals alert: fiper (both over) or bonferroni (any, each at alpha/K)")
    s.add_argument("--folds", type=int, help="folds of the cross-fitted detection figures (default 5)")
    s.add_argument("--n-bootstrap", type=int, help="AUROC bootstrap resamples (default 10000)")
    s.add_argument("--n-permutation", type=int, help="label permutations of the p-value (default 10000)")
    s.add_argument("--seed", type=int, help="seed of the resampling and the band split")
    s.set_defaults(func=cmd_calibrate)

    s = sub.add_parser("study", help="replay recorded episodes through each alert rule (detection at the same alpha)")
    s.add_argument("records", nargs="?", help="JSONL of episode records (jepa-demo, jepa-policy eval --out) or of "
                                              "ingest records (decision/target/outcome)")
    s.add_argument("--synthetic", type=int, metavar="DECISIONS",
                   help="instead of a file: a synthetic task with this many decisions per episode")
    s.add_argument("--episodes", default="100,100", help="--synthetic: successes,failures (default 100,100)")
    s.add_argument("--where", action="append", metavar="KEY=VALUE",
                   help="keep only episode records with this field value, e.g. --where arm=jepa (repeatable)")
    s.add_argument("--alpha", type=float, help="guaranteed false-alert rate (default: the service's alpha)")
    s.add_argument("--window", type=int, help="running-median window (default: the service's)")
    s.add_argument("--debounce", type=int, help="consecutive values over the threshold (default: the service's)")
    s.add_argument("--shape", choices=["flat", "running-max"], help="threshold shape (default: the service's)")
    s.add_argument("--length-check", action="store_true",
                   help="instead of a file: the false-alert rate of fresh synthetic successes per length bin "
                        "(lengths 5-150 decisions), both rules, alpha 0.05 and 0.2 (or --alpha)")
    s.add_argument("--draws", type=int, default=200, help="--length-check: calibrations (default 200)")
    s.add_argument("--fresh", type=int, default=200, help="--length-check: fresh successes per calibration")
    s.add_argument("--successes", type=int, default=100, help="--length-check: successes per calibration")
    s.add_argument("--promise-min", type=int, default=1, metavar="N",
                   help="--length-check: calibration successes a length bin needs for a promise besides alpha's "
                        "own minimum (default 1, the service's: every bin that can carry it; e.g. 20 trades "
                        "promised lengths for detection)")
    s.add_argument("--short-share", type=_share, metavar="P",
                   help="--length-check: this share of the calibration's successes 5-20 decisions long, the rest "
                        "21-150 (mostly short successes, e.g. 0.75; default: all uniform in 5-150)")
    s.add_argument("--folds", type=int, default=5, help="cross-fitting folds within each checkpoint")
    s.add_argument("--seed", type=int, default=0, help="seed of the folds and the band split")
    s.add_argument("--json", action="store_true", help="print every figure as JSON")
    s.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (--length-check; for logs)")
    s.set_defaults(func=cmd_study)

    compare_cli.add_parser(sub)
    compare_cli.add_ceiling_parser(sub)

    s = sub.add_parser("report", help="per-task calibrations (pooled figure only as a warning)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_report)

    s = sub.add_parser("replay", help="recorded rollouts (`jepa-policy eval --keep-latents --out FILE`) into a "
                                      "running service over its HTTP API, as a robot sends them: the first ones "
                                      "as held-out labelled episodes, the rest live")
    s.add_argument("records", help="episode records with latents (JSONL, or .jsonl.gz)")
    s.add_argument("--task", required=True, help="the registered task they belong to")
    s.add_argument("--url", default="http://127.0.0.1:8765", help="the service (default http://127.0.0.1:8765)")
    s.add_argument("--api-key", help="a robot key (default: JEPA_POLICY_MONITOR_KEY)")
    s.add_argument("--held-out", type=_held_out, default=0.5, metavar="N|P",
                   help="the first N episodes (or share P of them) are sent as held-out labelled rollouts for "
                        "calibration, the rest live (default 0.5)")
    s.add_argument("--part", choices=["all", "held-out", "live"], default="all",
                   help="send only the held-out episodes (then calibrate), or only the live ones (default: all)")
    s.add_argument("--where", action="append", metavar="FIELD=VALUE",
                   help="keep only records with this field value, e.g. --where arm=jepa (repeatable)")
    s.add_argument("--prefix", default="", help="prepended to every episode id (e.g. the task's name)")
    s.add_argument("--robot", help="the robot named in the records (default: the key's)")
    s.add_argument("--checkpoint", help="the checkpoint they came from (a calibration per checkpoint)")
    s.add_argument("--group", help="the episodes' group (leave-one-group-out figures)")
    s.add_argument("--signals", metavar="A,B", help="named scores to send with each decision (the task must "
                                                    "register them), e.g. stac")
    s.add_argument("--in-flight", type=int, default=0, metavar="K",
                   help="send the last K live episodes without their outcome: the service and its dashboard see "
                        "them running (default 0)")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    s.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")
    s.set_defaults(func=cmd_replay)

    s = sub.add_parser("tasks-study", help="several tasks in one service over HTTP: each calibrated on its own "
                                           "held-out rollouts and alerted on live, beside one pooled threshold")
    s.add_argument("--task", action="append", required=True, metavar="TASK=RECORDS",
                   help="a task and its records with latents (`jepa-policy eval --keep-latents --out`, a pick "
                        "job's decisions.jsonl.gz); repeatable")
    s.add_argument("--where", action="append", metavar="FIELD=VALUE", help="keep only records with this field value")
    s.add_argument("--held-out", type=_share, default=0.5, metavar="P",
                   help="share of each file's episodes (its first ones) held out for calibration (default 0.5)")
    s.add_argument("--alpha", type=_share, default=0.1, help="the rule's false-alert rate (default 0.1)")
    s.add_argument("--rule", choices=["running", "band"], default="running", help="alert rule (default running)")
    s.add_argument("--keep", metavar="DIR", help="keep the service's database (DIR/tasks_study.db) and log: "
                                                 "`jepa-monitor serve` on it shows the tasks on the dashboard")
    s.add_argument("--in-flight", type=int, default=0, metavar="K",
                   help="send each task's last K live episodes without their outcome, so that a dashboard on the "
                        "kept database shows them running (default 0)")
    s.add_argument("--out", action="append", default=[], metavar="FILE.json|FILE.md|FILE.png",
                   help="also write the figures as JSON (.json), the tables as Markdown (.md) or each task's "
                        "peak NMSE against both thresholds (.png); repeatable")
    s.add_argument("--json", action="store_true", help="print the figures as JSON")
    s.add_argument("--no-progress", action="store_true", help="no progress bars on stderr (for logs)")
    s.set_defaults(func=cmd_tasks_study)

    s = sub.add_parser("bench", help="ingest throughput and latency against real servers, beside the framework's floor")
    s.add_argument("--dim", type=int, default=1024, help="latent dimension (default 1024: two 512-d cameras)")
    s.add_argument("--seconds", type=float, default=8.0, help="duration of each mode (service and floor each)")
    s.add_argument("--rounds", type=int, default=4,
                   help="alternating service/floor rounds per mode, so that both see the same load (default 4)")
    s.add_argument("--concurrency", type=int, default=8, help="connections sending one record per request")
    s.add_argument("--batch", type=int, default=64, help="decisions (each with its target) per batched request")
    s.add_argument("--batch-concurrency", type=int, default=2, help="connections sending batches")
    s.add_argument("--host", help="bench a server someone else started (with --port and --admin-key)")
    s.add_argument("--port", type=int, help="its port")
    s.add_argument("--admin-key", help="an admin key of that server: the bench registers its task and robot key")
    s.add_argument("--servers", type=int, default=1, help="server processes started on --database-url (2 on "
                                                           "PostgreSQL: checks that no update is lost)")
    s.add_argument("--workers", type=int, default=1, help="uvicorn workers per server started here")
    s.add_argument("--client-decisions", type=int, default=20_000, help="MonitorClient end-to-end decisions (0: skip)")
    s.add_argument("--no-floor", action="store_true", help="skip the bare FastAPI + SQLite comparison")
    s.add_argument("--json", action="store_true", help="print every number as JSON (the rows go to stderr)")
    s.add_argument("--out", metavar="FILE.json", help="also write every number to this file as JSON")
    s.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    s.set_defaults(func=cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # after parsing: --help needs neither SQLAlchemy nor pydantic
    from sqlalchemy.exc import DBAPIError

    from monitor_service.settings import unknown_variables

    for warning in unknown_variables():
        print(f"jepa-monitor: warning: {warning}", file=sys.stderr)
    try:
        return args.func(args)
    except (ValueError, LookupError, FileNotFoundError, RuntimeError) as exc:
        print(f"jepa-monitor: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except DBAPIError as exc:   # the database refused or could not be reached
        print(f"jepa-monitor: error: the database failed: {_one_line(exc.orig or exc).split(' [SQL')[0]}; check "
              "JEPA_MONITOR_DATABASE_URL / --database-url and that the database server runs", file=sys.stderr)
        return 2


def _one_line(exc: Exception) -> str:
    """A user error on one line; a settings validation error as 'field: problem' pairs."""
    from pydantic import ValidationError

    if isinstance(exc, ValidationError):
        return "; ".join(f"{'.'.join(map(str, e['loc'])) or 'settings'}: {e['msg']}" for e in exc.errors())
    return " ".join(str(exc).split())


if __name__ == "__main__":
    sys.exit(main())
