"""``jepa-monitor ceiling``: how far can ANY score of an episode's first decisions predict its outcome?

PushT's outcome is chaotic: a change nobody would call a fault (Gaussian pixel noise of std 4 of 255) flips 13-21
of 100 outcomes both ways (docs/failure_prediction.md). So the outcome of an episode is not a function of its first
``prefix`` decisions alone, and no monitor that sees only them can rank failures perfectly. This measures how far
from perfect the best one must stay, by experiment rather than by assumption:

- Draws: the same seeded episode run several times (records of ``jepa-policy eval --faults`` with
  ``sensor_noise:onset=S,draw=r,label=...`` for several r, beside the natural run, all on the same seeds), each
  identical up to env step S and given a different harmless perturbation after it. Every draw's first ``prefix``
  decisions must be equal, every signal's values bit for bit (checked here: a perturbation that starts too early
  is refused, naming the seed), so any score of the prefix gives all draws of a seed the same value, while their
  outcomes may differ.
- Population: every draw of every seed whose episodes reach ``prefix`` decisions (the length-controlled view of
  ``jepa-monitor compare``), labelled by its own outcome. AUROC over pairs of draws of DIFFERENT seeds (two draws of
  one seed share their prefix: no score can order them, and a real data set holds one outcome per prefix).
- The best score there is P(failure | prefix), the seed's own failure probability p_i. It is estimated two ways,
  which bracket the ceiling: ``plug_in`` scores each draw with p_i estimated from all of its seed's draws, its own
  outcome included (optimistic: it has seen the label); ``leave_one_out`` scores each draw with the failure
  fraction of its seed's OTHER draws (a noisy estimate of p_i that never saw the label: pessimistic; it tends to
  the ceiling as the draws per seed grow).
- Beside them, each signal's prefix-mean score (and ``stack``, compare's cross-fitted fusion, fitted on the
  natural draws) on the same population and pairs: what the monitors reach of the ceiling.
Confidence intervals: a percentile bootstrap over seeds (each seed with all its draws).
"""
from __future__ import annotations

from collections import defaultdict

import numpy as np
from scipy.stats import rankdata
from tqdm import tqdm

from monitor_service.offline import compare as cmp

NATURAL = "natural"


def _within_u(scores: np.ndarray, labels: np.ndarray) -> tuple[float, int]:
    """Mann-Whitney U of one cluster's own failure-success pairs (ties count 1/2) and the number of such pairs."""
    pos, neg = scores[labels == 1], scores[labels == 0]
    if not pos.size or not neg.size:
        return 0.0, 0
    above = pos[:, None] > neg[None, :]   # compared, not subtracted: inf - inf is NaN, inf == inf a tie as in ranks
    ties = pos[:, None] == neg[None, :]
    return float(above.sum() + 0.5 * ties.sum()), int(pos.size * neg.size)


def cross_cluster_auroc(scores: np.ndarray, labels: np.ndarray, clusters: np.ndarray) -> float | None:
    """P(score of a failure > score of a success) + 1/2 P(tie) over pairs from DIFFERENT clusters; None without such
    a pair. All pairs' U from ranks, less each cluster's own pairs."""
    scores, labels, clusters = (np.asarray(a) for a in (scores, labels, clusters))
    n1 = int(labels.sum())
    n0 = labels.size - n1
    if not n1 or not n0:
        return None
    u = rankdata(scores)[labels == 1].sum() - n1 * (n1 + 1) / 2
    pairs = n1 * n0
    for c in np.unique(clusters):
        m = clusters == c
        wu, wp = _within_u(scores[m], labels[m])
        u, pairs = u - wu, pairs - wp
    return float(u / pairs) if pairs else None


def _cluster_bootstrap(scores: np.ndarray, labels: np.ndarray, clusters: np.ndarray, n_bootstrap: int,
                       seed: int) -> list[float] | None:
    """Percentile 95 % CI of ``cross_cluster_auroc``, resampling whole clusters (a resampled cluster's copies are
    clusters of their own)."""
    if n_bootstrap < 1:
        return None
    ids = np.unique(clusters)
    members = [np.flatnonzero(clusters == c) for c in ids]
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(n_bootstrap):
        pick = rng.integers(0, ids.size, ids.size)
        rows = np.concatenate([members[i] for i in pick])
        copy = np.concatenate([np.full(members[i].size, j) for j, i in enumerate(pick)])
        v = cross_cluster_auroc(scores[rows], labels[rows], copy)
        if v is not None:
            values.append(v)
    if not values:
        return None
    lo, hi = np.percentile(values, [2.5, 97.5])
    return [float(lo), float(hi)]


def _same_prefix(a: cmp.Episode, b: cmp.Episode, prefix: int) -> str | None:
    """None if both episodes' first ``prefix`` decisions are equal (steps and every shared signal, NaN = NaN), else
    what differs."""
    if not np.array_equal(a.steps[:prefix], b.steps[:prefix]):
        return "decision steps"
    for name in sorted(set(a.values) & set(b.values)):
        if not np.array_equal(a.values[name][:prefix], b.values[name][:prefix], equal_nan=True):
            return f"signal {name!r}"
    return None


def _draws(episodes: list[cmp.Episode], prefix: int,
           notes: list[str] | None = None) -> dict[str, dict[int, list[cmp.Episode]]]:
    """{group: {seed: its draws in the view}}, each seed with at least two draws whose prefixes agree; ValueError
    naming a seed whose draws differ within the prefix. ``notes`` gets a line for every seed left out and why."""
    notes = [] if notes is None else notes
    by = defaultdict(lambda: defaultdict(list))
    for e in episodes:
        by[e.group][e.seed].append(e)
    out = {}
    for group, seeds in sorted(by.items()):
        kept, single, short = {}, 0, 0
        for seed, draws in sorted(seeds.items()):
            regimes = [d.regime for d in draws]
            if len(set(regimes)) < len(regimes):
                twice = sorted(r for r in regimes if regimes.count(r) > 1)[0]
                raise ValueError(f"{group} seed {seed}: two records of regime {twice!r}; give each draw its own "
                                 "label, e.g. sensor_noise:onset=80,draw=2,label=draw2")
            reach = {d.n_decisions >= prefix for d in draws}
            if len(reach) > 1:
                raise ValueError(f"{group} seed {seed}: some draws reach {prefix} decisions and some do not, so their "
                                 f"first {prefix} decisions differ; start the perturbation after them (onset >= "
                                 f"{prefix * cmp.N_ACTION_STEPS} env steps for PushT)")
            if reach != {True}:
                short += 1
                continue
            if len(draws) < 2:
                single += 1
                continue
            for d in draws[1:]:
                what = _same_prefix(draws[0], d, prefix)
                if what is None:
                    continue
                late = prefix * cmp.N_ACTION_STEPS
                fix = (f"its onset ({d.onset}) is already after them, so the runs themselves differ: the same "
                       "checkpoint, detectors and device for every draw, and a deterministic run (--workers 0)"
                       if d.onset is not None and d.onset >= late else
                       f"start its perturbation after them, e.g. sensor_noise:onset={late},draw=1 (onset of this one: "
                       f"{d.onset})")
                raise ValueError(f"{group} seed {seed}: draws {draws[0].regime!r} and {d.regime!r} differ in the first "
                                 f"{prefix} decisions ({what}); a draw must leave them as they were: {fix}")
            kept[seed] = draws
        if short:
            notes.append(f"{group}: {short} seeds left out: their episodes end before {prefix} decisions")
        if single:
            notes.append(f"{group}: {single} seeds left out: one draw each (records of one checkpoint must name it "
                         "alike in every file: a group is arm:checkpoint)")
        if kept:
            out[group] = kept
    if not out:
        longest = max(e.n_decisions for e in episodes)
        if longest < prefix:
            raise ValueError(f"no episode reaches {prefix} decisions (the longest has {longest}): use --prefix "
                             f"{longest} or less")
        groups = sorted(by)
        raise ValueError(f"no seed has two or more draws reaching {prefix} decisions (groups read: "
                         f"{', '.join(groups)}; one checkpoint's records must name it alike in every file): give "
                         "the natural records and the same seeds under sensor_noise:onset=80,draw=1,label=draw1 (and "
                         "more draws) of jepa-policy eval --faults ... --faults-only")
    return out


def ceiling(episodes: list[cmp.Episode], prefix: int = cmp.PREFIX, n_bootstrap: int = 2000, seed: int = 0,
            signals=None, folds: int = 5, progress: bool = False) -> dict:
    """Per group (checkpoint): the outcome-predictability ceiling of the first ``prefix`` decisions and each
    signal's AUROC on the same draws (module docstring). ``progress``: a bar of the AUROC rows (each with its
    bootstrap) on stderr."""
    notes: list[str] = []
    result = {"prefix": prefix, "groups": {}, "notes": notes}
    kept = _draws(episodes, prefix, notes)
    if signals is not None:
        known = {n for seeds in kept.values() for draws in seeds.values() for d in draws for n in d.values}
        unknown = sorted(set(signals) - known - {cmp.STACK})
        if unknown:
            raise ValueError(f"--signals: no record carries {', '.join(map(repr, unknown))}; the records carry "
                             f"{', '.join(sorted(known))} (and {cmp.STACK})")
    bar = tqdm(desc="ceiling", unit="row", disable=not progress)
    for group, seeds in kept.items():
        rows = [(s, d) for s, draws in seeds.items() for d in draws]
        clusters = np.array([s for s, _ in rows])
        y = np.array([0 if d.success else 1 for _, d in rows])
        if y.min() == y.max():
            raise ValueError(f"{group}: all {y.size} draws {'failed' if y[0] else 'succeeded'}; an AUROC needs both "
                             "failures and successes (more seeds, or a task whose episodes can fail)")
        fails = {s: sum(not d.success for d in draws) for s, draws in seeds.items()}
        count = {s: len(draws) for s, draws in seeds.items()}
        plug_in = np.array([fails[s] / count[s] for s, _ in rows])
        loo = np.array([(fails[s] - yi) / (count[s] - 1) for (s, _), yi in zip(rows, y)])
        mixed = sum(0 < fails[s] < count[s] for s in seeds)

        def row(scores, name_seed, keep=None):
            keep = np.ones(len(rows), bool) if keep is None else keep
            bar.update()
            return {"auroc": cross_cluster_auroc(scores[keep], y[keep], clusters[keep]),
                    "ci": _cluster_bootstrap(scores[keep], y[keep], clusters[keep], n_bootstrap, seed + name_seed)}

        out = {"seeds": len(seeds), "draws": sum(count.values()), "draws_per_seed": [min(count.values()),
                                                                                     max(count.values())],
               "regimes": sorted({d.regime for _, d in rows}),
               "onsets": sorted({d.onset for _, d in rows if d.onset is not None}),
               "failure_rate": float(y.mean()), "seeds_mixed": mixed, "seeds_mixed_fraction": mixed / len(seeds),
               "ceiling": {"plug_in": row(plug_in, 1), "leave_one_out": row(loo, 2)}, "signals": {}}
        first = [draws[0] for draws in seeds.values()]
        every = sorted(set.union(*(set(e.values) for e in first)))
        names = every if signals is None else [n for n in signals if n != cmp.STACK]
        for i, name in enumerate(names):
            per_seed = {s: cmp.episode_score(draws[0].values[name][:prefix]) if name in draws[0].values else None
                        for s, draws in seeds.items()}
            keep = np.array([per_seed[s] is not None for s, _ in rows])
            missing = sum(v is None for v in per_seed.values())
            if missing:
                notes.append(f"{group}: {name} left out for {missing} of {len(seeds)} seeds (not recorded, or NaN "
                             f"in all of the first {prefix} decisions)")
            if not keep.any():
                continue
            scores = np.array([per_seed[s] if per_seed[s] is not None else np.nan for s, _ in rows])
            out["signals"][name] = row(scores, 10 + i, keep)
        natural = [d for draws in seeds.values() for d in draws if d.regime == NATURAL]
        wanted = signals is None or cmp.STACK in signals
        members = cmp.stack_members(every)
        if wanted and len(natural) < len(seeds):
            notes.append(f"{group}: no {cmp.STACK} row: it is fitted on the natural run of every seed and "
                         f"{len(seeds) - len(natural)} seeds have none (give the natural records too)")
        elif wanted and len(members) < 2:
            notes.append(f"{group}: no {cmp.STACK} row: it needs two or more non-control signals")
        if wanted and len(natural) == len(seeds) and len(members) > 1:   # fitted on the natural draws only
            cmp.assign_folds(natural, folds, seed)
            stacked = cmp.stacked_scores(natural, members, prefix)
            per_seed = {natural[i].seed: v for i, v in stacked.items()}
            keep = np.array([s in per_seed for s, _ in rows])
            if keep.any():
                scores = np.array([per_seed.get(s, np.nan) for s, _ in rows])
                out["signals"][cmp.STACK] = {**row(scores, 3, keep), "members": members}
        result["groups"][group] = out
    bar.close()
    return result


def _fmt(r: dict) -> str:
    if r.get("auroc") is None:
        return "-"
    ci = r.get("ci")
    return f"{r['auroc']:.3f}" + (f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else "")


def summary_text(result: dict) -> str:
    lines = []
    for group, g in result["groups"].items():
        lo, hi = g["draws_per_seed"]
        lines += [f"{group}: {g['seeds']} seeds reaching {result['prefix']} decisions, {g['draws']} draws "
                  f"({lo}-{hi} per seed; regimes {', '.join(g['regimes'])}), failure rate {g['failure_rate']:.3f}; "
                  f"outcome differs between draws of {g['seeds_mixed']} seeds ({g['seeds_mixed_fraction']:.1%})",
                  f"  ceiling of any score of the first {result['prefix']} decisions (AUROC over pairs of different "
                  f"seeds): leave-one-out {_fmt(g['ceiling']['leave_one_out'])}, plug-in "
                  f"{_fmt(g['ceiling']['plug_in'])}"]
        for name, r in sorted(g["signals"].items(), key=lambda kv: -(kv[1]["auroc"] or 0)):
            lines.append(f"  {name:20s} {_fmt(r)}")
    lines += [f"note: {n}" for n in result.get("notes", [])]
    return "\n".join(lines)
