"""``jepa-monitor compare``: its arguments (argparse only, so ``jepa-monitor --help`` stays quick) and its run;
the comparison itself is ``monitor_service/offline/compare.py``."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

HELP = ("every failure signal and alert rule on the same recorded episodes (natural failures, faults, benign "
        "shift): AUROC with CI, TPR/TNR/balanced accuracy, detection time, both calibrations, cross-fitted")


def add_parser(sub) -> argparse.ArgumentParser:
    """Register ``compare`` on the ``jepa-monitor`` sub-parsers."""
    s = sub.add_parser("compare", help=HELP, description=HELP)
    s.add_argument("records", nargs="+", help="episode records (JSONL, .gz too) of `jepa-policy eval --faults all "
                                              "--out FILE`, one file per checkpoint or several")
    s.add_argument("--where", action="append", metavar="KEY=VALUE",
                   help="keep only records with this field value, e.g. --where arm=jepa (repeatable; a key "
                        "given twice keeps either value)")
    s.add_argument("--alpha", type=float, default=0.1, help="false-alert rate the rules are calibrated at (0.1)")
    s.add_argument("--folds", type=int, default=5, help="cross-fitting folds (default 5)")
    s.add_argument("--prefix", type=int, default=10, help="decisions of the length-controlled view (default 10)")
    s.add_argument("--rules", default="default,fast",
                   help="rule settings: default (band, window 5, debounce 2: the service's), fast (band, window 1, "
                        "debounce 1)")
    s.add_argument("--views", default="prefix,whole", help="prefix (length-controlled) and/or whole episodes")
    s.add_argument("--signals", help="comma-separated signals to compare (default: every one the records hold)")
    s.add_argument("--aggregate", default="mean", choices=("mean", "max", "median", "max3"),
                   help="the ranking score of an episode: the signal's mean (default), max, median or max3 (the "
                        "peak of a 3-decision running mean) over the view's decisions")
    s.add_argument("--bootstrap", type=int, default=2000, help="AUROC bootstrap resamples (default 2000)")
    s.add_argument("--seed", type=int, default=0, help="seed of the folds, the band split and the bootstrap")
    s.add_argument("--json", action="store_true", help="print every figure as JSON instead of the summary")
    s.add_argument("--out", action="append", default=[], metavar="FILE.json|FILE.md",
                   help="write every figure as JSON (.json, with the natural-failure ROC curves: python3 -m "
                        "monitor_service.offline.figures draws them) or the tables as Markdown (.md); repeatable")
    s.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")
    s.set_defaults(func=run)
    return s


def run(args) -> int:
    from monitor_service.offline.compare import compare, load_records, markdown, parse_where, summary_text

    t0 = time.perf_counter()
    where = parse_where(args.where)
    if args.folds < 2:
        raise ValueError(f"--folds must be >= 2 for cross-fitting, got {args.folds}")
    if args.prefix < 1:
        raise ValueError(f"--prefix must be >= 1 decision, got {args.prefix}")
    views = tuple(v.strip() for v in args.views.split(",") if v.strip())
    if not views or set(views) - {"prefix", "whole"}:
        raise ValueError(f"--views takes prefix and/or whole, got {args.views!r}")
    check_out(args.out, (".json", ".md"))
    episodes = load_records(args.records, where)
    result = compare(episodes, alpha=args.alpha, folds=args.folds, prefix=args.prefix, seed=args.seed,
                     n_bootstrap=args.bootstrap, rule_names=tuple(r.strip() for r in args.rules.split(",")),
                     views=views, signals=[s.strip() for s in args.signals.split(",")] if args.signals else None,
                     aggregate=args.aggregate, progress=not args.no_progress)
    result["seconds"] = round(time.perf_counter() - t0, 1)
    for path in args.out:
        Path(path).write_text(markdown(result) if path.endswith(".md") else json.dumps(result, indent=1))
    print(json.dumps(result, indent=1) if args.json else summary_text(result))
    print(f"\n{len(episodes)} episodes compared in {result['seconds']} s", file=sys.stderr)
    return 0


def check_out(paths, suffixes: tuple[str, ...]) -> None:
    """Every --out names a file of a known kind in an existing folder (checked before the work, not after it)."""
    for path in paths:
        if not path.endswith(suffixes):
            raise ValueError(f"--out {path}: name a {' or '.join(suffixes)} file (the suffix picks what is written)")
        if Path(path).is_dir() or not Path(path).parent.is_dir():
            raise ValueError(f"--out {path}: give a file in an existing folder")


CEILING_HELP = ("how far any score of an episode's first decisions can predict its outcome: the same seeds run "
                "again under a harmless perturbation that starts after those decisions (sensor_noise:onset=80,"
                "draw=r), the outcome ceiling (AUROC) beside each signal's")


def add_ceiling_parser(sub) -> argparse.ArgumentParser:
    """Register ``ceiling`` on the ``jepa-monitor`` sub-parsers."""
    s = sub.add_parser("ceiling", help=CEILING_HELP, description=CEILING_HELP)
    s.add_argument("records", nargs="+",
                   help="episode records (JSONL, .gz too): the natural run and each draw on the same seeds, e.g. "
                        "jepa-policy eval --faults 'sensor_noise:onset=80,draw=1,label=draw1;...' --faults-only")
    s.add_argument("--where", action="append", metavar="KEY=VALUE",
                   help="keep only records with this field value, e.g. --where arm=jepa (repeatable; a key "
                        "given twice keeps either value)")
    s.add_argument("--prefix", type=int, default=10, help="decisions every score may see (default 10)")
    s.add_argument("--signals", help="comma-separated signals to set beside the ceiling (default: every one)")
    s.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples over seeds (default 2000)")
    s.add_argument("--seed", type=int, default=0, help="seed of the bootstrap and the stack's folds")
    s.add_argument("--json", action="store_true", help="print every figure as JSON instead of the summary")
    s.add_argument("--out", metavar="FILE.json", help="write every figure as JSON")
    s.add_argument("--no-progress", action="store_true", help="no progress bar on stderr (for logs)")
    s.set_defaults(func=run_ceiling)
    return s


def run_ceiling(args) -> int:
    from monitor_service.offline.outcome_ceiling import ceiling, summary_text
    from monitor_service.offline.compare import load_records, parse_where

    t0 = time.perf_counter()
    where = parse_where(args.where)
    if args.prefix < 1:
        raise ValueError(f"--prefix must be >= 1 decision, got {args.prefix}")
    if args.bootstrap < 0 or 0 < args.bootstrap < 100:
        raise ValueError(f"--bootstrap must be 0 (no intervals) or >= 100 resamples (a 95 % interval from fewer is "
                         f"noise), got {args.bootstrap}")
    check_out([args.out] if args.out else [], (".json",))
    episodes = load_records(args.records, where)
    result = ceiling(episodes, prefix=args.prefix, n_bootstrap=args.bootstrap, seed=args.seed,
                     signals=[s.strip() for s in args.signals.split(",")] if args.signals else None,
                     progress=not args.no_progress)
    result["seconds"] = round(time.perf_counter() - t0, 1)
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1) if args.json else summary_text(result))
    print(f"\n{len(episodes)} episodes read in {result['seconds']} s", file=sys.stderr)
    return 0
