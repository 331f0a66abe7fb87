"""Per-decision failure scores computed beside z_hat, and the detector state fitted after the policy.

Every score is non-negative, larger = riskier, and known when the decision is made (the future-consistency NMSE
waits k steps for its target and lives in ``evaluate.py``):

- ``stac``: temporal action consistency (Sentinel's STAC, for a deterministic policy). A decision at step t
  predicts a_t .. a_{t+H-1}; the previous one, ``n`` steps earlier, predicted a_{t-n} .. a_{t-n+H-1}. Both
  cover the H - n steps t .. t-n+H-1, and the score is the mean over those steps of the Euclidean distance of
  the two plans in normalised action units (the policy's own [-1, 1] scaling):
  stac_t = 1/(H-n) sum_{i<H-n} || a^t_i - a^{t-n}_{i+n} ||_2. Needs no fitted state; undefined (NaN) at an
  episode's first decision.
- embedding out-of-distribution scores on the fused embedding c_t (the policy's observation embedding), from
  state fitted on the training set's c_t after the policy (``fit_detectors``), with x = (c_t - mean) / std:
  - ``rnd``: random network distillation (FIPER's OOD score): a fixed random network f and a predictor g trained
    to imitate it on the training embeddings; rnd = mean_j (g(x)_j - f(x)_j)^2;
  - ``pca_kmeans``: FAIL-Detect's PCA + k-means baseline: x projected on the leading principal components of the
    training embeddings, the distance to the nearest of K k-means centres there;
  - ``mahalanobis``: a Gaussian density score, (c - mean)^T Sigma^-1 (c - mean) / d with the Ledoit-Wolf shrunk
    covariance of the training embeddings (about 1 in distribution).
- ``nmse_white`` (an attempt to sharpen our own signal; scored when the target arrives): the
  prediction error whitened per latent dimension by the training set's error scale,
  mean_j ((z_hat_j - z_j) / s_j)^2, with s_j the RMS of z_hat_j - z_j over the training windows.

The fitted state is a ``.npz`` of plain numeric arrays beside the checkpoint (``detector_path``), read with
``allow_pickle=False`` after each member's header is checked (numeric dtype, bounded size, the expected shape),
so a crafted or truncated file is refused in one line and nothing in it can run code. It names the checkpoint it
was fitted for (SHA-256 of the file); another checkpoint refuses it.
"""
from __future__ import annotations

import hashlib
import json
import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from sklearn.cluster import KMeans
from sklearn.covariance import LedoitWolf
from torch import nn
from tqdm import tqdm

from jepa_policy.dataset import WindowDataset

FORMAT = "jepa-policy-detectors/1"
EMBEDDING_SCORES = ("rnd", "pca_kmeans", "mahalanobis")
DECISION_SCORES = ("stac", *EMBEDDING_SCORES)
MAX_ELEMENTS = 50_000_000          # per array: far above any real fit, far below what would exhaust memory
_ALLOWED_DTYPES = (np.dtype("<f4"), np.dtype("<f8"), np.dtype("|u1"))


class DetectorFileError(ValueError):
    """A detector file that cannot be used: not plain data, truncated, inconsistent, or fitted elsewhere."""


# ----------------------------------------------------------------------------- the scores (pure functions)

def stac(chunk: np.ndarray, previous: np.ndarray | None, shift: int) -> np.ndarray:
    """Mean Euclidean distance over the overlapping steps of two normalised action chunks (module docstring).

    ``chunk`` and ``previous``: (H, A) or (B, H, A); ``shift``: env steps between the two decisions. NaN where
    there is no previous chunk or no overlap."""
    chunk = np.asarray(chunk, dtype=np.float64)
    lead = chunk.shape[:-2]
    horizon = chunk.shape[-2]
    if previous is None or not 0 < shift < horizon:
        return np.full(lead, np.nan)
    previous = np.asarray(previous, dtype=np.float64)
    if previous.shape != chunk.shape:
        raise ValueError(f"chunks of different shapes {previous.shape} and {chunk.shape}")
    diff = chunk[..., : horizon - shift, :] - previous[..., shift:, :]
    return np.sqrt((diff * diff).sum(axis=-1)).mean(axis=-1)


def whitened_error(z_hat: np.ndarray, z: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """mean_j ((z_hat_j - z_j) / scale_j)^2 per row."""
    r = (np.asarray(z_hat, np.float64) - np.asarray(z, np.float64)) / np.asarray(scale, np.float64)
    return np.mean(r * r, axis=-1)


def _mlp_tail(x: np.ndarray, rest: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """A LeakyReLU(0.01) MLP in numpy (the same network as ``_torch_mlp``) after its first layer's affine map
    ``x``: the activation, then ``rest``'s layers, no activation after the last."""
    for w, b in rest:
        x = np.maximum(x, 0.01 * x) @ w + b       # LeakyReLU(0.01) between layers
    return x


@dataclass(frozen=True, eq=False)
class EmbeddingDetectors:
    """The fitted state of the embedding scores, as plain arrays (see the module docstring for each score).
    Immutable: ``score`` caches a fused matrix built from the arrays on its first call, so the fields cannot be
    reassigned and the arrays are read-only (a change after the first score would otherwise be ignored by all
    but ``mean``, silently); ``dataclasses.replace`` makes a changed copy with its own cache."""

    mean: np.ndarray                 # (d,) of the training c_t
    std: np.ndarray                  # (d,)
    whiten: np.ndarray               # (d, d): (c - mean) @ whiten has identity covariance (Ledoit-Wolf)
    pca: np.ndarray                  # (d, p): principal directions of x = (c - mean) / std
    centres: np.ndarray              # (K, p): k-means centres in the PCA space
    rnd_target: list[tuple[np.ndarray, np.ndarray]]
    rnd_predictor: list[tuple[np.ndarray, np.ndarray]]
    future_scale: np.ndarray | None  # (d_z,) RMS of z_hat - z over the training windows (arms with a future head)
    meta: dict

    def __post_init__(self) -> None:
        layers = [a for w, b in (*self.rnd_target, *self.rnd_predictor) for a in (w, b)]
        for array in (self.mean, self.std, self.whiten, self.pca, self.centres, self.future_scale, *layers):
            if isinstance(array, np.ndarray):
                array.setflags(write=False)

    def score(self, c: np.ndarray) -> dict[str, np.ndarray]:
        """The embedding scores of c_t rows (B, d) -> {name: (B,)}.

        Every first step is affine in c - mean, so one matrix product and one bias do them all (``_fused``): the
        whitening (scaled by 1/sqrt(d)), the PCA projection of x = (c - mean) / std, its k-means cross terms
        -2 p.C_k, and both RND networks' first layers; then the rest of the two small networks. The same numbers
        as scoring each in turn (float32 rounding aside) in about a third of the numpy calls: right after the
        policy's forward pass each call runs with cold caches, so the count is the cost a decision pays
        (the goal: at most 5 % of a decision)."""
        c = np.asarray(c, dtype=np.float32)
        if c.ndim != 2 or c.shape[1] != self.mean.size:
            raise ValueError(f"score needs c_t rows of shape (B, {self.mean.size}), got {list(c.shape)}; pass "
                             "c[None] for one row, and the embeddings of the checkpoint the detectors were fitted on")
        fused, bias, cuts, centres_sq = self._fused()
        h = (c - self.mean) @ fused + bias   # centred first: no cancellation
        w, p, cross, t, g = (h[:, a:b] for a, b in zip(cuts[:-1], cuts[1:]))
        g = _mlp_tail(g, self.rnd_predictor[1:])
        f = _mlp_tail(t, self.rnd_target[1:])
        d2 = (cross + centres_sq).min(axis=1) + np.einsum("ij,ij->i", p, p)
        return {"rnd": np.mean((g - f) ** 2, axis=1).astype(np.float64),
                "pca_kmeans": np.sqrt(np.maximum(d2, 0.0)).astype(np.float64),
                "mahalanobis": np.einsum("ij,ij->i", w, w).astype(np.float64)}

    def _fused(self) -> tuple[np.ndarray, np.ndarray, list[int], np.ndarray]:
        """W = [whiten / sqrt(d) | pca / std | -2 (pca / std) C^T | RND target W0 / std | RND predictor W0 / std]
        (d, .), the bias [0 | 0 | 0 | b_target | b_predictor] added to (c - mean) @ W, the column cuts between the
        blocks and the centres' squared norms; built once per object from its arrays."""
        cached = self.__dict__.get("_fused_cache")
        if cached is None:
            scale = 1.0 / self.std[:, None].astype(np.float64)
            pca = self.pca * scale
            blocks = [self.whiten / np.sqrt(self.mean.size), pca, -2.0 * pca @ self.centres.T.astype(np.float64),
                      self.rnd_target[0][0] * scale, self.rnd_predictor[0][0] * scale]
            fused = np.concatenate([np.asarray(b, np.float64) for b in blocks], axis=1)
            shift = np.concatenate([np.zeros(sum(b.shape[1] for b in blocks[:3])), self.rnd_target[0][1],
                                    self.rnd_predictor[0][1]])
            cuts = np.cumsum([0] + [b.shape[1] for b in blocks]).tolist()
            cached = (fused.astype(np.float32), shift.astype(np.float32),
                      cuts, (self.centres.astype(np.float64) ** 2).sum(axis=1).astype(np.float32))
            self.__dict__["_fused_cache"] = cached
        return cached

    # -------------------------------------------------------------- the file
    def arrays(self) -> dict[str, np.ndarray]:
        out = {"mean": self.mean, "std": self.std, "whiten": self.whiten, "pca": self.pca, "centres": self.centres}
        for prefix, layers in (("rnd_target", self.rnd_target), ("rnd_predictor", self.rnd_predictor)):
            for i, (w, b) in enumerate(layers):
                out[f"{prefix}_w{i}"], out[f"{prefix}_b{i}"] = w, b
        if self.future_scale is not None:
            out["future_scale"] = self.future_scale
        return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}

    def save(self, path: str | Path) -> Path:
        """Write the arrays and the metadata (JSON bytes as a uint8 array) atomically."""
        path = Path(path)
        meta = json.dumps(self.meta, sort_keys=True).encode()
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.frombuffer(meta, dtype=np.uint8), **self.arrays())
        tmp.replace(path)
        return path


def detector_path(checkpoint: str | Path) -> Path:
    """Where the detectors of a checkpoint live: ``<checkpoint stem>.detectors.npz`` beside it."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.stem + ".detectors.npz")


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _read_members(path: Path) -> dict[str, np.ndarray]:
    """Every array of an .npz after checking its header: a plain numeric dtype and a bounded size."""
    out = {}
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                name = info.filename
                if not name.endswith(".npy") or "/" in name:
                    raise DetectorFileError(f"member {name!r} is not an array")
                with archive.open(info) as f:
                    try:
                        version = np.lib.format.read_magic(f)
                        shape, fortran, dtype = (np.lib.format.read_array_header_1_0(f) if version == (1, 0)
                                                 else np.lib.format.read_array_header_2_0(f))
                    except ValueError as exc:
                        raise DetectorFileError(f"member {name!r} is not a plain .npy array "
                                                f"({str(exc).splitlines()[0][:80]})") from None
                    if dtype not in _ALLOWED_DTYPES or fortran:
                        raise DetectorFileError(f"array {name[:-4]!r} has dtype {dtype} (only little-endian float32, "
                                                "float64 and uint8 are plain data here; an object array could run "
                                                "code when read)")
                    if math.prod(shape) > MAX_ELEMENTS:
                        raise DetectorFileError(f"array {name[:-4]!r} declares shape {shape}, over "
                                                f"{MAX_ELEMENTS} elements")
                    f.seek(0)
                    out[name[:-4]] = np.lib.format.read_array(f, allow_pickle=False)
    except DetectorFileError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise DetectorFileError(f"not a complete detector file (truncated, or not an .npz: "
                                f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    return out


def load_detectors(path: str | Path, checkpoint: str | Path | None = None) -> EmbeddingDetectors:
    """The detectors of ``path``, checked: plain numeric arrays of consistent shapes, finite, the format tag, and
    (``checkpoint``) fitted for that checkpoint file. Raises DetectorFileError in one line naming the fix."""
    path = Path(path)
    fix = f"refit with `jepa-policy fit-detectors --checkpoint {checkpoint or 'CHECKPOINT'} --dataset DATASET`"
    if not path.is_file():
        raise FileNotFoundError(f"detector file {path} does not exist; {fix}")
    try:
        arrays = _read_members(path)
        if "meta" not in arrays or arrays["meta"].dtype != np.uint8 or arrays["meta"].ndim != 1:
            raise DetectorFileError("it has no metadata")
        try:
            meta = json.loads(arrays.pop("meta").tobytes().decode())
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise DetectorFileError("its metadata is not JSON") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise DetectorFileError(f"its format tag is not {FORMAT!r}")
        detectors = _from_arrays(arrays, meta)
        if checkpoint is not None and meta.get("checkpoint_sha256") != file_sha256(checkpoint):
            raise DetectorFileError(f"it was fitted for another checkpoint (step {meta.get('checkpoint_step')}, "
                                    f"sha256 {str(meta.get('checkpoint_sha256'))[:12]}), not {Path(checkpoint).name}")
    except DetectorFileError as exc:
        raise DetectorFileError(f"refused detector file {path}: {exc}; {fix}") from None
    return detectors


def _from_arrays(arrays: dict[str, np.ndarray], meta: dict) -> EmbeddingDetectors:
    for name, value in arrays.items():
        if value.dtype == np.uint8:
            raise DetectorFileError(f"array {name!r} is not floating point")
        if not np.isfinite(value).all():
            raise DetectorFileError(f"array {name!r} holds NaN or inf")

    def get(name: str, ndim: int) -> np.ndarray:
        if name not in arrays:
            raise DetectorFileError(f"array {name!r} is missing")
        value = arrays[name].astype(np.float32)
        if value.ndim != ndim:
            raise DetectorFileError(f"array {name!r} has {value.ndim} dimensions, not {ndim}")
        return value

    def layers(prefix: str) -> list[tuple[np.ndarray, np.ndarray]]:
        out, i, width = [], 0, d
        while f"{prefix}_w{i}" in arrays:
            w, b = get(f"{prefix}_w{i}", 2), get(f"{prefix}_b{i}", 1)
            if w.shape[0] != width or b.shape != (w.shape[1],):
                raise DetectorFileError(f"{prefix} layer {i} has shapes {w.shape}, {b.shape} after width {width}")
            out.append((w, b))
            width, i = w.shape[1], i + 1
        if not out:
            raise DetectorFileError(f"the {prefix} network is missing")
        return out

    mean = get("mean", 1)
    d = mean.size
    std, whiten, pca, centres = get("std", 1), get("whiten", 2), get("pca", 2), get("centres", 2)
    if std.shape != (d,) or (std <= 0).any() or whiten.shape != (d, d) or pca.shape[0] != d \
            or centres.shape[1] != pca.shape[1] or centres.shape[0] < 1:
        raise DetectorFileError(f"inconsistent shapes: mean {mean.shape}, std {std.shape}, whiten {whiten.shape}, "
                                f"pca {pca.shape}, centres {centres.shape} (std must be positive)")
    target, predictor = layers("rnd_target"), layers("rnd_predictor")
    if target[-1][0].shape[1] != predictor[-1][0].shape[1]:
        raise DetectorFileError("the RND target and predictor end in different widths")
    future = get("future_scale", 1) if "future_scale" in arrays else None
    if future is not None and (future <= 0).any():
        raise DetectorFileError("future_scale must be positive")
    known = {"mean", "std", "whiten", "pca", "centres", "future_scale"} | {
        f"{p}_{k}{i}" for p in ("rnd_target", "rnd_predictor") for k in "wb" for i in range(16)}
    extra = sorted(set(arrays) - known)
    if extra:
        raise DetectorFileError(f"unexpected arrays {extra}")
    if meta.get("embedding_dim") != d:
        raise DetectorFileError(f"its metadata says embedding_dim {meta.get('embedding_dim')}, the arrays {d}")
    return EmbeddingDetectors(mean, std, whiten, pca, centres, target, predictor, future, meta)


# ----------------------------------------------------------------------------- fitting after the policy

def _torch_mlp(sizes: list[int], generator: torch.Generator) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        linear = nn.Linear(a, b)
        with torch.no_grad():
            linear.weight.copy_(torch.randn(b, a, generator=generator) * math.sqrt(2.0 / a))
            linear.bias.zero_()
        layers.append(linear)
        if i < len(sizes) - 2:
            layers.append(nn.LeakyReLU(0.01))
    return nn.Sequential(*layers)


def _numpy_layers(net: nn.Sequential) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(m.weight.detach().T.numpy().copy(), m.bias.detach().numpy().copy())
            for m in net if isinstance(m, nn.Linear)]


def fit_rnd(x: np.ndarray, out_dim: int = 32, hidden: int = 128, epochs: int = 60, batch: int = 256,
            lr: float = 1e-3, seed: int = 0) -> tuple[list, list]:
    """A random target network and a predictor trained (Adam, MSE) to match it on the rows of ``x``."""
    gen = torch.Generator().manual_seed(seed)
    target = _torch_mlp([x.shape[1], hidden, out_dim], gen)
    predictor = _torch_mlp([x.shape[1], hidden, hidden, out_dim], gen)
    data = torch.from_numpy(np.asarray(x, np.float32))
    with torch.no_grad():
        goal = target(data)
    opt = torch.optim.Adam(predictor.parameters(), lr=lr)
    order_gen = torch.Generator().manual_seed(seed + 1)
    for _ in range(epochs):
        for idx in torch.randperm(len(data), generator=order_gen).split(batch):
            loss = ((predictor(data[idx]) - goal[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    return _numpy_layers(target), _numpy_layers(predictor)


def fit_embedding_detectors(c: np.ndarray, future_errors: np.ndarray | None = None, clusters: int = 64,
                            variance: float = 0.95, max_components: int = 32, seed: int = 0,
                            meta: dict | None = None) -> EmbeddingDetectors:
    """Fit every embedding score on training embeddings ``c`` (N, d) (and the future-error scale from the
    training prediction errors ``future_errors`` (N, d_z), when given)."""
    c = np.asarray(c, dtype=np.float64)
    if c.ndim != 2 or c.shape[0] < max(2 * clusters, c.shape[1] + 2):
        raise ValueError(f"need at least max(2 x {clusters} clusters, d + 2) training embeddings, got {c.shape}; "
                         "fit on a larger dataset")
    mean = c.mean(axis=0)
    std = np.maximum(c.std(axis=0), 1e-6 * max(float(c.std()), 1e-12))
    x = (c - mean) / std
    precision = LedoitWolf().fit(c).precision_
    whiten = np.linalg.cholesky((precision + precision.T) / 2)
    _, s, vt = np.linalg.svd(x - x.mean(axis=0), full_matrices=False)
    share = np.cumsum(s * s) / np.sum(s * s)
    p = int(min(max_components, np.searchsorted(share, variance) + 1, c.shape[1]))
    pca = vt[:p].T
    kmeans = KMeans(n_clusters=clusters, n_init=4, random_state=seed).fit(x @ pca)
    target, predictor = fit_rnd(x, seed=seed)
    future = None
    if future_errors is not None:
        future = np.sqrt(np.mean(np.asarray(future_errors, np.float64) ** 2, axis=0))
        future = np.maximum(future, 1e-6 * max(float(future.max()), 1e-12))
    meta = {"format": FORMAT, "embedding_dim": int(c.shape[1]), "samples": int(c.shape[0]), "seed": seed,
            "clusters": clusters, "pca_components": p, "pca_variance": float(share[p - 1]), **(meta or {})}
    return EmbeddingDetectors(mean.astype(np.float32), std.astype(np.float32), whiten.astype(np.float32),
                              pca.astype(np.float32), kmeans.cluster_centers_.astype(np.float32), target, predictor,
                              None if future is None else future.astype(np.float32), meta)


@torch.inference_mode()
def training_embeddings(policy, demos, samples: int = 8192, seed: int = 0, batch_size: int = 256,
                        progress: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """c_t of up to ``samples`` training windows (a seeded sample), and z_hat - E_rgb(o_{t+k}) of the same
    windows for arms with a future head (else None); ``progress``: a bar of the batches on stderr."""
    model = policy.model
    if not hasattr(model, "representations"):
        raise ValueError(f"arm {model.cfg.arm!r} has no fused embedding c_t to fit detectors on (the JEPA family "
                         "has: jepa, mip and the ablation arms)")
    cfg = model.cfg   # the windows the model was trained on: its history, chunk and future horizon k
    windows = WindowDataset.from_demos(demos, obs_steps=cfg.obs_steps, horizon=cfg.horizon, future_k=cfg.future_k)
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(len(windows), size=min(samples, len(windows)), replace=False))
    cs, errors = [], []
    for start in tqdm(range(0, len(idx), batch_size), desc="fit-detectors", unit="batch", disable=not progress):
        batch = windows[idx[start:start + batch_size]]
        obs = {k: v.to(policy.device) for k, v in batch["obs"].items()}
        views = model.representations(obs)
        cs.append(views["c_t"].double().cpu().numpy())
        if "z_hat" in views:
            future = {k: v.to(policy.device) for k, v in batch["future_obs"].items()}
            errors.append((views["z_hat"] - model.encode_future(future)).double().cpu().numpy())
    return np.concatenate(cs), (np.concatenate(errors) if errors else None)


def fit_detectors(policy, checkpoint: str | Path, demos, samples: int = 8192, seed: int = 0,
                  out: str | Path | None = None, progress: bool = False) -> Path:
    """Fit the embedding detectors of ``policy`` (loaded from ``checkpoint``) on its training set ``demos`` and
    write them beside the checkpoint (or to ``out``); returns the file. ``progress``: a bar of the embedding
    batches on stderr."""
    c, errors = training_embeddings(policy, demos, samples, seed, progress=progress)
    detectors = fit_embedding_detectors(c, errors, seed=seed, meta={
        "checkpoint_sha256": file_sha256(checkpoint), "checkpoint_step": policy.checkpoint_step,
        "arm": policy.model.cfg.arm, "task": policy.spec.name})
    return detectors.save(out or detector_path(checkpoint))
