"""The paper's audits of a trained policy, on fixed sample manifests so every checkpoint sees the same inputs.

Collapse (Sec. 4.9), computed in float64. For a representation matrix X (N samples x D features), centred over
samples, with eigenvalues lambda_1 >= ... >= lambda_D of X_c^T X_c:
- effective rank = exp(entropy of lambda / sum(lambda))  (Roy & Vetterli), between 1 and D;
- top-eigenvalue share = lambda_1 / sum(lambda);
- TE32 = 1 - sum_{i<=32} lambda_i / sum(lambda): spectral energy outside the leading 32 directions; the
  paper's pre-specified low-rank boundary is TE32 = 0.05, for views of 384 or more dimensions.
  A view of D < 384 dimensions is judged with the same criterion scaled to its width: TE_k < 0.05 with
  k = max(1, round(32 D / 384)) leading directions (the paper's 32 of 384), so a 64-d view looks at its top 5
  and a 16-d one at its top 1; TE32 itself is 0 by construction at D <= 32 and says nothing there. Every
  result states its boundary (``low_rank_boundary``).
Views: ``c_t`` (the fused representation, width 384 at paper size: the audited one), ``e_rgb`` (the pooled image
features E_rgb, 1,024-d) and ``z_hat`` (the predictor's output).

Retrieval (Sec. 4.9): does z_hat pick its own realized target E_rgb(o_{t+k}) out of a pool of 256 candidates
(itself and 255 other targets of the manifest, drawn once per query from a seed)? Recall@1, Recall@5 and the
median rank under NMSE, with the candidate-label permutation null (the true candidate drawn uniformly from
the pool) and its p-value, overall and split by whether the window's future frame was clamped at the episode's
end (then o_{t+k} is the last frame, an easier target).

Gradient interaction (Sec. 4.5): per parameter group the norms of the action-loss and future-loss gradients,
their ratio and cosine; the cross-gradients (the future loss on the action head, the action loss on the future
head); and the paper's gradient share on the parameters that produce the action readout.
"""
from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import torch
from tqdm import tqdm

from jepa_envs.tasks.fault_replay import IMAGE_FAULTS, fault_frames
from jepa_envs.tasks.faults import faults_for
from jepa_policy.dataset import WindowDataset
from monitor_service.scoring import nmse_rows

TE32_BOUNDARY = 0.05
PAPER_WIDTH = 384    # c_t's width at paper size, where the paper's TE32 boundary was set
VIEWS = {
    "c_t": "fused representation c_t = Fuse([E_rgb(o_t), s_t]) (the paper's audited view)",
    "e_rgb": "pooled image features E_rgb(o_t)",
    "z_hat": "predictor output z_hat (refined future latent)",
}
POOL = 256


def centred_spectrum(x: np.ndarray) -> np.ndarray:
    """Eigenvalues of X_c^T X_c in descending order (float64), via the singular values of X_c."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"need a (N >= 2, D) representation matrix, got shape {x.shape}")
    xc = x - x.mean(axis=0, keepdims=True)
    s = np.linalg.svd(xc, compute_uv=False)
    return np.sort(s * s)[::-1]


def boundary_directions(dim: int, k: int = 32) -> int:
    """Leading directions the low-rank criterion counts for a ``dim``-wide view: the paper's k = 32 from 384
    dimensions up, the same share of the width below (at least 1)."""
    return k if dim >= PAPER_WIDTH else max(1, round(k * dim / PAPER_WIDTH))


def spectral_stats(x: np.ndarray, k: int = 32) -> dict:
    """Effective rank, top-eigenvalue share and TE_k of the centred matrix (Sec. 4.9), and whether it is low-rank
    by the criterion scaled to its dimension (module docstring), with that criterion stated."""
    lam = centred_spectrum(x)
    dim = int(np.asarray(x).shape[1])
    k_dim = boundary_directions(dim, k)
    boundary = {"te_k": k_dim, "below": TE32_BOUNDARY,
                "meaning": f"low-rank when the directions beyond the leading {k_dim} of {dim} hold less than "
                           f"{TE32_BOUNDARY:.0%} of the spectral energy (the paper's TE{k} < {TE32_BOUNDARY} at "
                           f"{PAPER_WIDTH} dimensions{'' if dim >= PAPER_WIDTH else ', scaled to this width'})"}
    total = lam.sum()
    if total <= 0:  # every sample identical: complete collapse
        return {"effective_rank": 1.0, "top_share": 1.0, f"te{k}": 0.0, "dim": dim, "te_scaled": 0.0,
                "low_rank": True, "low_rank_boundary": boundary}
    p = lam / total
    nz = p[p > 0]
    te = max(0.0, float(1.0 - p[:k].sum()))   # exactly 0 when D <= k (not -1e-16)
    te_scaled = max(0.0, float(1.0 - p[:k_dim].sum()))
    return {"effective_rank": float(np.exp(-(nz * np.log(nz)).sum())), "top_share": float(p[0]),
            f"te{k}": te, "dim": dim, "te_scaled": te_scaled, "low_rank": te_scaled < TE32_BOUNDARY,
            "low_rank_boundary": boundary}


def manifest(num_windows: int, samples: int = 4096, seed: int = 0) -> np.ndarray:
    """Fixed, sorted sample of window indices, so every checkpoint is audited on the same inputs."""
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(num_windows, size=min(samples, num_windows), replace=False))


def _batches(windows: WindowDataset, idx: np.ndarray, batch_size: int, device, progress: str = ""):
    """(obs, future_obs) batches of the manifest ``idx``; ``progress``: a bar on stderr of that name."""
    starts = range(0, len(idx), batch_size)
    for start in tqdm(starts, desc=progress, unit="batch", disable=not progress):
        batch = windows[idx[start:start + batch_size]]
        yield ({k: v.to(device) for k, v in batch["obs"].items()},
               {k: v.to(device) for k, v in batch["future_obs"].items()})


@torch.inference_mode()
def audit_checkpoint(policy, demos, samples: int = 4096, seed: int = 0, batch_size: int = 256,
                     progress: bool = False) -> dict:
    """Spectral statistics of each view (``VIEWS``) on a fixed manifest of dataset windows (``progress``: a bar
    of its batches on stderr)."""
    model = policy.model
    if not hasattr(model, "representations"):
        raise ValueError(f"arm {model.cfg.arm!r} has no fused representation c_t to audit (the collapse audit "
                         "reads the JEPA family: jepa, mip and the ablation arms)")
    windows = WindowDataset.from_demos(demos)
    idx = manifest(len(windows), samples, seed)
    views: dict[str, list[np.ndarray]] = {}
    for obs, _ in _batches(windows, idx, batch_size, policy.device, "collapse audit" if progress else ""):
        for name, x in model.representations(obs).items():
            views.setdefault(name, []).append(x.double().cpu().numpy())
    return {"samples": int(len(idx)), "seed": seed, "primary": "c_t",
            "views": {name: {"what": VIEWS[name], **spectral_stats(np.concatenate(xs))}
                      for name, xs in views.items()}}


def nmse_matrix(z_hat: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(Q, P) d_NMSE of each query against each of its P candidates: z_hat (Q, D), targets (Q, P, D)."""
    q, p, d = targets.shape
    queries = np.broadcast_to(z_hat[:, None, :], targets.shape)
    return nmse_rows(queries.reshape(q * p, d), targets.reshape(q * p, d)).reshape(q, p)


def candidate_pools(n: int, pool: int, seed: int) -> np.ndarray:
    """(n, pool) manifest positions: column 0 is the query's own target, the rest other samples (seeded)."""
    if n < pool:
        raise ValueError(f"retrieval needs at least {pool} manifest samples, got {n}; use a larger dataset or "
                         "--pool smaller")
    rng = np.random.default_rng(seed)
    others = np.empty((n, pool - 1), dtype=np.int64)
    for i in range(n):
        draw = rng.choice(n - 1, size=pool - 1, replace=False)
        others[i] = draw + (draw >= i)      # skip the query itself
    return np.concatenate([np.arange(n)[:, None], others], axis=1)


def retrieval_stats(scores: np.ndarray, permutations: int = 1000, seed: int = 0) -> dict:
    """Recall@1/@5, median rank of column 0 (the true target; lower score = better) and the label-permutation
    null: the true column drawn uniformly, Recall@1 recomputed, p = (1 + #null >= observed) / (1 + B)."""
    scores = np.asarray(scores, dtype=np.float64)
    n, pool = scores.shape
    if n == 0:
        return {"queries": 0}
    order_rank = scores.argsort(axis=1, kind="stable").argsort(axis=1) + 1    # rank of every candidate
    rank = order_rank[:, 0]
    recall1 = float(np.mean(rank == 1))
    rng = np.random.default_rng(seed)
    null = np.array([np.mean(order_rank[np.arange(n), rng.integers(0, pool, n)] == 1) for _ in range(permutations)])
    return {"queries": int(n), "pool": int(pool), "recall_at_1": recall1, "recall_at_5": float(np.mean(rank <= 5)),
            "median_rank": float(np.median(rank)), "chance_recall_at_1": 1.0 / pool,
            "null_recall_at_1_mean": float(null.mean()),
            "permutation_p": float((1 + np.sum(null >= recall1 - 1e-12)) / (1 + permutations))}


@torch.inference_mode()
def retrieval_audit(policy, demos, samples: int = 4096, pool: int = POOL, seed: int = 0, permutations: int = 1000,
                    batch_size: int = 256, progress: bool = False) -> dict:
    """Sec. 4.9 retrieval on a fixed manifest: z_hat against its own realized target among ``pool`` candidates
    (``progress``: a bar of its batches on stderr)."""
    model = policy.model
    if not model.cfg.has_future_token:
        raise ValueError(f"arm {model.cfg.arm!r} predicts no future latent: retrieval needs a future head")
    windows = WindowDataset.from_demos(demos)
    idx = manifest(len(windows), samples, seed)
    z_hat, z_real = [], []
    for obs, future in _batches(windows, idx, batch_size, policy.device, "retrieval audit" if progress else ""):
        z_hat.append(model.predict(obs, want_future=True)[1].double().cpu().numpy())
        z_real.append(model.encode_future(future).double().cpu().numpy())
    z_hat, z_real = np.concatenate(z_hat), np.concatenate(z_real)
    pools = candidate_pools(len(idx), pool, seed)
    scores = np.concatenate([nmse_matrix(z_hat[s:s + 64], z_real[pools[s:s + 64]])
                             for s in range(0, len(idx), 64)])
    clamped = windows.index.clamped[idx]
    out = {"samples": int(len(idx)), "seed": seed, "score": "d_NMSE (lower is the better match)",
           "all": retrieval_stats(scores, permutations, seed)}
    for name, mask in (("future_in_episode", ~clamped), ("future_clamped_at_end", clamped)):
        out[name] = retrieval_stats(scores[mask], permutations, seed) if mask.any() else {"queries": 0}
    return out


def gradient_interaction(model, batch, generator: torch.Generator | None = None) -> dict:
    """Sec. 4.5 on one batch: per parameter group ||g_act||, ||g_future||, their ratio and cosine; the
    cross-gradients; and the gradient share on the action readout (``PolicyModel.gradient_share``).

    The loss terms are the weighted ones training sums; nothing is written to ``.grad``."""
    if not hasattr(model, "parameter_groups"):
        raise ValueError(f"arm {model.cfg.arm!r} has no future loss to interact with (JEPA family only)")
    terms, _ = model.loss_terms(batch, generator)
    groups = model.parameter_groups()
    params = [p for ps in groups.values() for p in ps]
    readout = {id(p) for p in model.action_readout_parameters()}
    out = {"arm": model.cfg.arm, "groups": {}}
    if "future" not in terms:
        out["gradient_share"] = 0.0
        return out
    g_act = torch.autograd.grad(terms["act"], params, retain_graph=True, allow_unused=True)
    g_fut = torch.autograd.grad(terms["future"], params, allow_unused=True)

    def flat(grads, members):
        parts = [g.float().flatten() for g, p in zip(grads, params) if id(p) in members and g is not None]
        return torch.cat(parts) if parts else torch.zeros(0)

    for name, members in groups.items():
        ids = {id(p) for p in members}
        a, f = flat(g_act, ids), flat(g_fut, ids)
        na, nf = float(a.norm()) if a.numel() else 0.0, float(f.norm()) if f.numel() else 0.0
        cos = float(torch.dot(a, f) / (a.norm() * f.norm())) if na > 0 and nf > 0 and a.numel() == f.numel() else None
        out["groups"][name] = {"act_norm": na, "future_norm": nf,
                               "ratio": nf / na if na > 0 else (math.inf if nf > 0 else 0.0), "cosine": cos}
    ra, rf = flat(g_act, readout), flat(g_fut, readout)
    out["gradient_share"] = float(rf.norm() / ra.norm().clamp_min(1e-30)) if ra.numel() else 0.0
    out["cross"] = {"future_loss_on_action_head": out["groups"]["action_head"]["future_norm"],
                    "action_loss_on_future_head": out["groups"].get("future_head", {}).get("act_norm", 0.0)}
    return out


def gradient_audit(policy, demos, batches: int = 8, batch_size: int = 64, seed: int = 0,
                   progress: bool = False) -> dict:
    """``gradient_interaction`` averaged over ``batches`` seeded batches of a dataset (train-mode noise;
    ``progress``: a bar of the batches on stderr)."""
    model = policy.model
    windows = WindowDataset.from_demos(demos)
    rng = np.random.default_rng(seed)
    rows = []
    model.train()
    try:
        for b in tqdm(range(batches), desc="gradient audit", unit="batch", disable=not progress):
            idx = np.sort(rng.choice(len(windows), size=min(batch_size, len(windows)), replace=False))
            batch = windows[idx]
            batch = {k: ({kk: vv.to(policy.device) for kk, vv in v.items()} if isinstance(v, dict)
                         else v.to(policy.device)) for k, v in batch.items()}
            torch.manual_seed(seed * 1000 + b)
            rows.append(gradient_interaction(model, batch))
    finally:
        model.eval()
    return {**average_interaction(rows), "batches": batches, "batch_size": batch_size, "seed": seed}


def average_interaction(rows: list[dict]) -> dict:
    """The mean of each number over rows of ``gradient_interaction`` (cosines of groups that have them)."""
    out = {"arm": rows[0]["arm"], "gradient_share": float(np.mean([r["gradient_share"] for r in rows])),
           "groups": {}}
    for name in rows[0]["groups"]:
        out["groups"][name] = {}
        for key in ("act_norm", "future_norm", "ratio", "cosine"):
            vals = [r["groups"][name][key] for r in rows if r["groups"][name][key] is not None]
            out["groups"][name][key] = float(np.mean(vals)) if vals else None
    if "cross" in rows[0]:
        out["cross"] = {k: float(np.mean([r["cross"][k] for r in rows])) for k in rows[0]["cross"]}
    return out


VISIBILITY_ALPHA = 0.1
TEN_DECISIONS = 10   # the decisions an episode-level alpha is spread over (the prefix view's length)


def _faulted_batch(spec, obs: dict, future: dict, fault: dict, seeds) -> tuple[dict, dict]:
    """A batch's observation histories and future frames as ``fault`` ({"name", options}) shows them (onset before
    the history's first frame), each window its own episode of seed ``seeds[b]``; low-dim inputs untouched."""
    name, options = fault["name"], {k: v for k, v in fault.items() if k not in ("name", "label")}
    keys = spec.image_keys
    steps = obs[keys[0]].shape[1]
    hist = {k: [] for k in keys}
    fut = {k: [] for k in keys}
    for b, seed in enumerate(seeds):
        frames = [{k: obs[k][b, j].numpy() for k in keys} for j in range(steps)]
        frames.append({k: future[k][b].numpy() for k in keys})
        shown = fault_frames(spec, frames, name, int(seed), **options)
        for k in keys:
            hist[k].append(np.stack([f[k] for f in shown[:steps]]))
            fut[k].append(shown[steps][k])
    return ({**obs, **{k: torch.from_numpy(np.stack(v)) for k, v in hist.items()}},
            {k: torch.from_numpy(np.stack(v)) for k, v in fut.items()})


def _exceed(values: np.ndarray, threshold: float) -> float:
    return float(np.mean(values > threshold))


@torch.inference_mode()
def visibility_audit(policy, demos, faults=None, samples: int = 1024, seed: int = 0, batch_size: int = 128,
                     alpha: float = VISIBILITY_ALPHA, progress: bool = False) -> dict:
    """How far each image fault moves what the monitor reads, on a fixed manifest of dataset windows, without the
    simulator: each window's frames shown as the fault shows them (``fault_frames``; each window its own episode,
    so the fault's draws vary over windows), beside the clean windows.

    Per fault, over the windows:
    - ``encoder``: d_NMSE(E(o_{t+k}), E(f(o_{t+k}))), the change of the realized latent itself, and its ratio to
      the scene's own change over the k steps, d_NMSE(E(o_t), E(o_{t+k})) (``persistence``);
    - ``straddle``: the NMSE of the clean prediction against the faulted target, what a decision scores when the
      onset falls between it and its target (the best case of NMSE: at most one decision per onset has it);
    - ``inside``: the NMSE of the prediction from a faulted history against the faulted target, what every later
      decision scores;
    - each embedding score of the checkpoint's fitted detectors (RND, PCA-kmeans, Mahalanobis) on the faulted
      history.
    Each is compared with the same windows' clean values: the median per-window ratio, and the fraction of
    windows above two quantiles of the clean values: (1 - ``alpha``) (``exceed_decision``: by construction
    ``alpha`` of the clean windows are above it, a single decision's chance of standing out at a per-decision
    false-alarm rate of ``alpha``) and (1 - ``alpha`` / ``TEN_DECISIONS``) (``exceed_ten_decisions``, still a
    per-decision rate: the budget an episode-level rate of ``alpha`` leaves each of 10 decisions; the service's
    rules spend alpha over whole episodes, often more decisions). A score whose rates sit at those levels does not
    tell the faulted windows from clean ones; high rates say a score moves, not that the fault's failures will be
    caught in time (the policy's reaction, the rollout's states and the rule decide that: rollouts,
    ``jepa-policy eval --faults`` and ``jepa-monitor compare``). Faults that change the simulation or the actions
    are refused (``fault_frames``).

    ``faults``: names, or {"name", "label"?, options...} dicts (``jepa-policy eval --faults``' syntax parsed), e.g.
    a larger camera shift; None: every image fault of the task at its default options. Rows are keyed by label
    (default: the name)."""
    model, spec = policy.model, policy.spec
    if not model.cfg.has_future_token:
        raise ValueError(f"arm {model.cfg.arm!r} predicts no future latent: the visibility audit reads its NMSE; "
                         "give a checkpoint of an arm with a future head (jepa)")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
    if samples < 1:
        raise ValueError(f"the visibility audit needs at least 1 window, got samples={samples}")
    chosen = [f if isinstance(f, dict) else {"name": f}
              for f in (faults or [f for f in faults_for(spec) if f in IMAGE_FAULTS])]
    refused = [f["name"] for f in chosen if f["name"] not in IMAGE_FAULTS]
    if refused:
        raise ValueError(f"the visibility audit applies image faults to recorded frames; {refused} "
                         f"{'is' if len(refused) == 1 else 'are'} not one (image faults: {IMAGE_FAULTS}); measure "
                         "the others with jepa-policy eval --faults")
    labelled = {str(f.get("label", f["name"])): f for f in chosen}
    if len(labelled) < len(chosen):
        raise ValueError("two audited faults share a label; name one with label=..., e.g. camera_shift:pixels=6,"
                         "label=camera_6px")
    windows = WindowDataset.from_demos(demos)
    idx = manifest(len(windows), samples, seed)
    first = windows[idx[:1]]["future_obs"]
    for fault in labelled.values():   # bad options refused before any window is encoded
        _faulted_batch(spec, {k: v[:, None] for k, v in first.items()}, first, fault, [seed])
    detectors = policy.detectors

    def to(d: dict) -> dict:
        return {k: v.to(policy.device) for k, v in d.items()}

    def scored(obs: dict) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        _, z_hat, c = model.predict_embedded(to(obs), want_future=True)
        extra = detectors.score(c.cpu().numpy()) if detectors is not None else {}
        return z_hat.double().cpu().numpy(), extra

    clean: dict[str, list] = defaultdict(list)
    faulted: dict[str, dict[str, list]] = {label: defaultdict(list) for label in labelled}
    starts = range(0, len(idx), batch_size)
    for start in tqdm(starts, desc="visibility audit", unit="batch", disable=not progress):
        rows = idx[start:start + batch_size]
        batch = windows[rows]
        obs, future = batch["obs"], batch["future_obs"]
        z_hat, extra = scored(obs)
        z_fut = model.encode_future(to(future)).double().cpu().numpy()
        z_now = model.encode_future(to({k: obs[k][:, -1] for k in spec.image_keys})).double().cpu().numpy()
        clean["nmse"].append(nmse_rows(z_hat, z_fut))
        clean["persistence"].append(nmse_rows(z_now, z_fut))
        for name, v in extra.items():
            clean[name].append(np.asarray(v, np.float64))
        for f, fault in labelled.items():
            f_obs, f_future = _faulted_batch(spec, obs, future, fault, seed * 1_000_003 + rows)
            zf_hat, f_extra = scored(f_obs)
            zf_fut = model.encode_future(to(f_future)).double().cpu().numpy()
            faulted[f]["encoder"].append(nmse_rows(z_fut, zf_fut))
            faulted[f]["straddle"].append(nmse_rows(z_hat, zf_fut))
            faulted[f]["inside"].append(nmse_rows(zf_hat, zf_fut))
            for name, v in f_extra.items():
                faulted[f][name].append(np.asarray(v, np.float64))
    base = {k: np.concatenate(v) for k, v in clean.items()}
    levels = {"exceed_decision": 1 - alpha, "exceed_ten_decisions": 1 - alpha / TEN_DECISIONS}
    q = {k: {level: float(np.quantile(v, p)) for level, p in levels.items()} for k, v in base.items()}
    out = {"samples": int(len(idx)), "seed": seed, "alpha": alpha, "k": int(model.cfg.future_k), "levels": levels,
           "clean": {k: {"median": float(np.median(v)), "quantiles": q[k]} for k, v in base.items()},
           "faults": {}}
    for f, fault in labelled.items():
        got = {k: np.concatenate(v) for k, v in faulted[f].items()}
        row = {"fault": fault, "encoder_median": float(np.median(got["encoder"])),
               "encoder_vs_persistence": float(np.median(got["encoder"] / np.maximum(base["persistence"], 1e-12)))}
        for view in ("straddle", "inside"):
            row[view] = {"median_ratio": float(np.median(got[view] / np.maximum(base["nmse"], 1e-12))),
                         **{level: _exceed(got[view], t) for level, t in q["nmse"].items()}}
        for name in sorted(base.keys() - {"nmse", "persistence"}):
            row[name] = {"median_ratio": float(np.median(got[name] / np.maximum(np.abs(base[name]), 1e-12))),
                         **{level: _exceed(got[name], t) for level, t in q[name].items()}}
        out["faults"][f] = row
    return out
