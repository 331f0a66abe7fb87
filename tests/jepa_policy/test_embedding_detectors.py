"""Per-decision failure scores (jepa_policy/detectors.py): each against its reference formula, the detector file's
trust boundary, and the acting runtime and the rollouts carrying the scores."""
from __future__ import annotations

import json
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from sklearn.cluster import KMeans
from sklearn.covariance import LedoitWolf

from jepa_envs.datasets.hdf5 import load_dataset
from jepa_policy.cli import main as policy_main
from jepa_policy.detectors import (DetectorFileError, _torch_mlp, detector_path, fit_embedding_detectors,
                                   load_detectors, stac, whitened_error)
from jepa_policy.evaluate import evaluate
from jepa_policy.policy import Policy
from jepa_policy.train import load_config, train


# ----------------------------------------------------------------------------- the formulas

def test_stac_is_the_mean_distance_over_the_overlap():
    rng = np.random.default_rng(0)
    prev, cur = rng.normal(size=(16, 2)), rng.normal(size=(16, 2))
    want = np.mean([np.sqrt(((cur[i] - prev[i + 8]) ** 2).sum()) for i in range(8)])
    assert stac(cur, prev, 8) == pytest.approx(want, rel=1e-12)
    want3 = np.mean([np.linalg.norm(cur[i] - prev[i + 3]) for i in range(13)])
    assert stac(cur, prev, 3) == pytest.approx(want3, rel=1e-12)
    batch = stac(np.stack([cur, prev]), np.stack([prev, cur]), 8)
    assert batch.shape == (2,) and batch[0] == pytest.approx(want, rel=1e-12)
    assert stac(prev, prev.copy(), 0).item() != stac(prev, prev.copy(), 0).item()   # NaN: no shift, no overlap
    assert np.isnan(stac(cur, None, 8)) and np.isnan(stac(cur, prev, 16))
    assert stac(np.tile(prev[8:], (2, 1)), prev, 8) == 0.0       # a plan that keeps the previous one: 0
    with pytest.raises(ValueError, match="different shapes"):
        stac(cur, prev[:10], 8)


def test_whitened_error_formula():
    z_hat, z, s = np.array([[1.0, 2.0, 3.0]]), np.array([[0.0, 2.0, 5.0]]), np.array([0.5, 1.0, 4.0])
    assert whitened_error(z_hat, z, s)[0] == pytest.approx(((1 / 0.5) ** 2 + 0 + (2 / 4) ** 2) / 3)


@pytest.fixture(scope="module")
def gaussian():
    rng = np.random.default_rng(1)
    mix = rng.normal(size=(8, 8)) * 0.3
    c = rng.normal(size=(800, 8)) @ (np.eye(8) + mix) + 2.0
    errors = rng.normal(size=(800, 5)) * np.array([0.1, 0.2, 0.5, 1.0, 2.0])
    return c, errors, fit_embedding_detectors(c, errors, clusters=8, seed=0, meta={"checkpoint_sha256": "x"})


def test_embedding_scores_match_their_references(gaussian):
    c, errors, det = gaussian
    rng = np.random.default_rng(2)
    probe = np.concatenate([c[:20], c[:20] + rng.normal(size=(20, 8)) * 3])
    got = det.score(probe)

    lw = LedoitWolf().fit(c)
    np.testing.assert_allclose(got["mahalanobis"], lw.mahalanobis(probe) / 8, rtol=2e-4)

    x = (probe - c.mean(0)) / c.std(0)
    _, _, vt = np.linalg.svd((c - c.mean(0)) / c.std(0), full_matrices=False)
    p = det.pca.shape[1]
    assert det.meta["pca_variance"] >= 0.95 and p <= 8
    proj = x @ vt[:p].T
    signs = np.sign(np.sum(vt[:p].T * det.pca, axis=0))          # a principal direction is defined up to sign
    km = KMeans(n_clusters=8, n_init=4, random_state=0).fit(((c - c.mean(0)) / c.std(0)) @ (vt[:p].T * signs))
    want = km.transform(proj * signs).min(axis=1)
    np.testing.assert_allclose(got["pca_kmeans"], want, rtol=2e-3, atol=2e-4)

    target = _torch_mlp([8, 128, 32], torch.Generator().manual_seed(0))   # the same seeded target network
    with torch.no_grad():
        for m, (w, b) in zip([m for m in target if isinstance(m, torch.nn.Linear)], det.rnd_target):
            np.testing.assert_allclose(m.weight.T.numpy(), w, rtol=1e-6)
        f = target(torch.from_numpy(x.astype(np.float32))).numpy()
    g = x.astype(np.float32)
    for i, (w, b) in enumerate(det.rnd_predictor):
        g = g @ w + b
        g = np.where(g > 0, g, 0.01 * g) if i < len(det.rnd_predictor) - 1 else g
    np.testing.assert_allclose(got["rnd"], np.mean((g - f) ** 2, axis=1), rtol=1e-4)
    for name in ("rnd", "pca_kmeans", "mahalanobis"):   # every score ranks the shifted probes above the training ones
        assert got[name][20:].mean() > 2 * got[name][:20].mean(), name
    np.testing.assert_allclose(det.future_scale, np.sqrt((errors ** 2).mean(0)), rtol=1e-5)


# ----------------------------------------------------------------------------- the file and its trust boundary

def test_round_trip(gaussian, tmp_path):
    _, _, det = gaussian
    path = det.save(tmp_path / "d.detectors.npz")
    back = load_detectors(path)
    probe = np.random.default_rng(3).normal(size=(5, 8))
    for name, value in det.score(probe).items():
        np.testing.assert_array_equal(back.score(probe)[name], value)
    assert back.meta == det.meta


def _members(path) -> dict[str, np.ndarray]:
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


def _rewrite(path, **changes) -> None:
    arrays = _members(path)
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    np.savez(path, **arrays)


class _Canary:
    """Unpickling this would write a file: a crafted detector must never get that far."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


@pytest.mark.parametrize("craft, message", [
    ("truncate", "not a complete detector file"),
    ("not_zip", "not a complete detector file"),
    ("object_array", "only little-endian float32, float64 and uint8 are plain data"),
    ("pickle_member", "member 'evil.npy' is not a plain .npy array"),
    ("int_array", "has dtype int64"),
    ("nan", "holds NaN or inf"),
    ("missing", "array 'whiten' is missing"),
    ("extra", "unexpected arrays ['payload']"),
    ("shape", "inconsistent shapes"),
    ("tag", "format tag"),
    ("huge", "over 50000000 elements"),
    ("subdir", "is not an array"),
])
def test_crafted_or_truncated_files_are_refused_in_one_line(gaussian, tmp_path, craft, message):
    _, _, det = gaussian
    path = det.save(tmp_path / "d.detectors.npz")
    canary = tmp_path / "pwned"
    if craft == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif craft == "not_zip":
        path.write_bytes(pickle.dumps(_Canary(canary)))
    elif craft == "object_array":
        _rewrite(path, mean=np.array([_Canary(canary)] * 8, dtype=object))
    elif craft == "pickle_member":
        with zipfile.ZipFile(path, "a") as z:
            z.writestr("evil.npy", pickle.dumps(_Canary(canary)))
    elif craft == "int_array":
        _rewrite(path, mean=np.arange(8))
    elif craft == "nan":
        _rewrite(path, mean=np.full(8, np.nan, np.float32))
    elif craft == "missing":
        _rewrite(path, whiten=None)
    elif craft == "extra":
        _rewrite(path, payload=np.zeros(3, np.float32))
    elif craft == "shape":
        _rewrite(path, whiten=np.eye(5, dtype=np.float32))
    elif craft == "tag":
        meta = json.dumps({**det.meta, "format": "something-else"}).encode()
        _rewrite(path, meta=np.frombuffer(meta, np.uint8))
    elif craft == "huge":   # a header that declares 10^10 floats: refused before anything is allocated
        header = b"{'descr': '<f4', 'fortran_order': False, 'shape': (100000, 100000), }"
        header += b" " * (63 - (len(header) + 10) % 64) + b"\n"
        with zipfile.ZipFile(path, "a") as z:
            z.writestr("big.npy", b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header)
    elif craft == "subdir":
        with zipfile.ZipFile(path, "a") as z:
            z.writestr("x/mean.npy", b"")
    with pytest.raises(DetectorFileError) as info:
        load_detectors(path)
    text = str(info.value)
    assert message in text and "\n" not in text and text.startswith(f"refused detector file {path}")
    assert "jepa-policy fit-detectors" in text
    assert not canary.exists()


# ----------------------------------------------------------------------------- runtime, rollouts, command line

@pytest.fixture(scope="module")
def checkpoint(pusht_demo_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("det_ckpt")
    demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
    result = train(load_config("PushT", "quick", out_dir=str(out), steps=3, warmup_steps=1), demos)
    return result["checkpoint"]


def test_fit_detectors_command_and_the_runtime_scores(checkpoint, pusht_demo_file, capsys):
    assert policy_main(["fit-detectors", "--checkpoint", str(checkpoint), "--dataset", str(pusht_demo_file),
                        "--samples", "200", "--device", "cpu"]) == 0
    path = detector_path(checkpoint)
    printed, err = capsys.readouterr()
    assert json.loads(printed)["detectors"] == str(path) and "fit-detectors: 100%" in err
    policy = Policy.from_checkpoint(checkpoint)          # the file beside the checkpoint is loaded
    assert policy.detectors is not None and policy.detectors.meta["samples"] == 200
    rng = np.random.default_rng(0)
    obs = lambda: {"top_image": rng.integers(0, 256, (32, 32, 3), dtype=np.uint8),   # noqa: E731
                   "agent_pos": rng.uniform(0, 512, 2).astype(np.float32)}
    decisions = []
    for _ in range(17):
        before = policy.last_decision
        policy.act(obs())
        if policy.last_decision is not before:
            decisions.append(policy.last_decision)
    first, second = decisions[0], decisions[1]
    assert set(first.scores) == {"stac", "rnd", "pca_kmeans", "mahalanobis"} and np.isnan(first.scores["stac"])
    f = policy.model.normalizer.fields["action"]
    norm = lambda a: a * f.scale.numpy().astype(np.float64) + f.offset.numpy().astype(np.float64)   # noqa: E731
    assert second.scores["stac"] == pytest.approx(float(stac(norm(second.actions), norm(first.actions), 8)), rel=1e-9)
    want = policy.detectors.score(second.embedding[None])
    assert all(second.scores[k] == pytest.approx(float(want[k][0])) for k in want)
    assert second.embedding.shape == (policy.model.cfg.width,)

    report = evaluate(policy, episodes=2, seed=5, num_envs=2, max_steps=20, fault={"name": "action_noise",
                                                                                      "onset": 9})
    for rec in report["records"]:
        assert rec["fault"] == "action_noise" and rec["fault_onset"] == 9
        d0, d1 = rec["decisions"][:2]
        assert d0["scores"]["stac"] is None and d1["scores"]["stac"] > 0
        assert {"rnd", "pca_kmeans", "mahalanobis"} <= set(d1["scores"]) and d1["nmse_white"] > 0

    other = Policy.from_checkpoint(checkpoint, detectors=False)
    assert other.detectors is None and set(evaluate(other, 1, 5, 1, max_steps=9)["records"][0]["decisions"][1]
                                           ["scores"]) == {"stac"}


def test_detectors_of_another_checkpoint_are_refused(checkpoint, pusht_demo_file, tmp_path, capsys):
    assert policy_main(["fit-detectors", "--checkpoint", str(checkpoint), "--dataset", str(pusht_demo_file),
                        "--samples", "200", "--device", "cpu", "--out", str(tmp_path / "mine.npz"),
                        "--no-progress"]) == 0
    assert capsys.readouterr().err == ""
    copy = tmp_path / "other.pt"
    copy.write_bytes(Path(checkpoint).read_bytes() + b"\0")           # another file (its digest differs)
    detector_path(copy).write_bytes((tmp_path / "mine.npz").read_bytes())
    with pytest.raises(DetectorFileError, match="fitted for another checkpoint"):
        Policy.from_checkpoint(copy)
    assert Policy.from_checkpoint(copy, detectors=False).detectors is None
    with pytest.raises(FileNotFoundError, match="fit-detectors"):
        load_detectors(tmp_path / "absent.npz")
    detector_path(copy).write_bytes(b"PK\x03\x04 not really")      # the command line: one line, exit code 2
    assert policy_main(["eval", "--checkpoint", str(copy), "--episodes", "1", "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "refused detector file" in err and "not a complete detector file" in err
