"""The paper's audits: collapse statistics (Sec. 4.9) against direct eigen-decompositions and known spectra,
retrieval against brute force, the gradient interaction against the arms' known gradient routes (Sec. 4.5)."""
import json

import numpy as np
import pytest
import torch
from _model_helpers import make_batch, tiny_model

from jepa_policy.audit import (audit_checkpoint, candidate_pools, centred_spectrum, gradient_interaction, manifest,
                               nmse_matrix, retrieval_stats, spectral_stats)
from jepa_policy.dataset import WindowDataset
from monitor_service.scoring import nmse_rows


def test_spectrum_equals_eigenvalues_of_centred_gram():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 40)) @ rng.normal(size=(40, 40)) + 5.0
    xc = x - x.mean(0)
    expected = np.sort(np.linalg.eigvalsh(xc.T @ xc))[::-1]
    np.testing.assert_allclose(centred_spectrum(x), expected, rtol=1e-9, atol=1e-9)


def test_stats_on_known_spectra():
    rng = np.random.default_rng(1)
    # 64 orthogonal directions with equal energy: effective rank 64, top share 1/64, TE32 = 1/2
    q, _ = np.linalg.qr(rng.normal(size=(64, 64)))
    x = np.concatenate([q, -q]) * 3.0
    s = spectral_stats(x)
    assert s["effective_rank"] == pytest.approx(64.0, rel=1e-9)
    assert s["top_share"] == pytest.approx(1 / 64, rel=1e-9)
    assert s["te32"] == pytest.approx(0.5, rel=1e-9) and not s["low_rank"]
    # rank one plus a constant offset: complete concentration in one direction
    line = np.outer(rng.normal(size=100), rng.normal(size=16)) + 7.0
    s = spectral_stats(line)
    assert s["effective_rank"] == pytest.approx(1.0, abs=1e-6) and s["top_share"] == pytest.approx(1.0)
    assert s["te32"] == pytest.approx(0.0, abs=1e-12) and s["low_rank"]
    # identical samples: the degenerate case is reported as collapsed, not as NaN
    assert spectral_stats(np.ones((10, 8)))["low_rank"]
    with pytest.raises(ValueError, match="representation matrix"):
        spectral_stats(np.ones(5))


def test_low_rank_boundary_scales_with_the_dimension():
    """With TE32 < 0.05 as the criterion any view of <= 32 dimensions is 'low-rank' (TE32 is 0 there),
    so random 16-d data was flagged. The criterion now counts k = 32 D / 384 leading directions below 384
    dimensions and states itself; full-rank random data passes, low-rank data is caught, at every width."""
    rng = np.random.default_rng(5)
    for dim, k in ((16, 1), (64, 5), (192, 16), (384, 32), (1024, 32)):
        full = spectral_stats(rng.normal(size=(2000, dim)))
        assert not full["low_rank"] and full["low_rank_boundary"]["te_k"] == k, dim
        assert f"leading {k} of {dim}" in full["low_rank_boundary"]["meaning"]
        rank = max(1, k // 2)   # energy in fewer directions than the boundary counts, plus a trace of noise
        low = rng.normal(size=(2000, rank)) @ rng.normal(size=(rank, dim)) + 1e-3 * rng.normal(size=(2000, dim))
        assert spectral_stats(low)["low_rank"], dim
    paper = spectral_stats(rng.normal(size=(2000, 384)))
    assert paper["te_scaled"] == paper["te32"]            # the paper's own criterion at its width


def test_manifest_is_fixed_and_bounded():
    a, b = manifest(10_000, 4096, seed=3), manifest(10_000, 4096, seed=3)
    assert np.array_equal(a, b) and len(np.unique(a)) == 4096 and a.max() < 10_000
    assert len(manifest(100, 4096)) == 100


# ----------------------------------------------------------------------------- retrieval (Sec. 4.9)

def test_candidate_pools_hold_the_query_first_and_distinct_others():
    pools = candidate_pools(300, 32, seed=1)
    assert pools.shape == (300, 32) and np.array_equal(pools[:, 0], np.arange(300))
    assert all(len(set(row)) == 32 and row[0] not in set(row[1:]) for row in pools.tolist())
    assert np.array_equal(pools, candidate_pools(300, 32, seed=1))
    with pytest.raises(ValueError, match="at least 256 manifest samples"):
        candidate_pools(100, 256, seed=0)


def test_retrieval_stats_against_brute_force_and_its_null():
    rng = np.random.default_rng(0)
    scores = rng.random((400, 16))
    scores[:200, 0] = -1.0          # half the queries rank their own target first
    out = retrieval_stats(scores, permutations=300, seed=0)
    ranks = np.array([1 + np.sum(row[1:] < row[0]) for row in scores])
    assert out["recall_at_1"] == pytest.approx(np.mean(ranks == 1))
    assert out["recall_at_5"] == pytest.approx(np.mean(ranks <= 5))
    assert out["median_rank"] == pytest.approx(np.median(ranks)) and out["chance_recall_at_1"] == 1 / 16
    assert out["null_recall_at_1_mean"] == pytest.approx(1 / 16, abs=0.02)
    assert out["permutation_p"] == pytest.approx(1 / 301)        # no permutation reaches 0.5
    chance = retrieval_stats(rng.random((400, 16)), permutations=300, seed=0)
    assert chance["permutation_p"] > 0.05                         # no signal: the null is not rejected


def test_nmse_matrix_is_the_paper_nmse_per_candidate():
    rng = np.random.default_rng(3)
    z_hat, targets = rng.normal(size=(5, 12)), rng.normal(size=(5, 7, 12))
    ref = [[np.sum(((z_hat[q] - targets[q, c]) / np.sqrt(np.mean(targets[q, c] ** 2))) ** 2) / 12
            for c in range(7)] for q in range(5)]
    np.testing.assert_allclose(nmse_matrix(z_hat, targets), ref, rtol=1e-12)


# ----------------------------------------------------------------------------- gradient interaction (Sec. 4.5)

@pytest.mark.parametrize("arm", ["jepa", "dual_independent", "backcut", "fwdcut", "mip"])
def test_gradient_interaction_routes_match_the_arms(arm):
    model = tiny_model(arm).train()
    batch = make_batch(model.cfg, batch=4)
    torch.manual_seed(0)
    out = gradient_interaction(model, batch)
    if arm == "mip":
        assert out["gradient_share"] == 0.0 and out["groups"] == {}
        return
    g = out["groups"]
    assert g["future_head"]["future_norm"] > 0 and g["action_head"]["act_norm"] > 0
    if arm == "dual_independent":      # no path from the future loss to the action stack or head
        assert g["action_stack"]["future_norm"] == 0.0 and g["action_head"]["future_norm"] == 0.0
        assert out["gradient_share"] == 0.0 and g["conditioning"]["future_norm"] > 0
    elif arm == "backcut":             # the future loss reaches h_z only
        assert g["trunk"]["future_norm"] == g["encoder"]["future_norm"] == g["conditioning"]["future_norm"] == 0.0
        assert out["gradient_share"] == 0.0
    else:
        assert g["trunk"]["future_norm"] > 0 and out["gradient_share"] > 0
        assert -1.0 <= g["trunk"]["cosine"] <= 1.0
    # the action loss reaches the future token's embedding only where action tokens may attend to it
    assert g["future_head"]["act_norm"] == out["cross"]["action_loss_on_future_head"]
    assert (g["future_head"]["act_norm"] > 0) == (arm in ("jepa", "backcut"))
    assert out["cross"]["future_loss_on_action_head"] == g["action_head"]["future_norm"]
    torch.manual_seed(0)
    assert out["gradient_share"] == pytest.approx(model.gradient_share(batch), rel=1e-5, abs=1e-12)


def test_gradient_interaction_leaves_grads_and_training_untouched():
    model = tiny_model("jepa").train()
    batch = make_batch(model.cfg)
    gradient_interaction(model, batch)
    assert all(p.grad is None for p in model.parameters())


def test_collapse_audit_views_on_a_trained_checkpoint(pusht_demo_file, tmp_path):
    from jepa_envs.datasets.hdf5 import load_dataset
    from jepa_policy.policy import Policy
    from jepa_policy.train import load_config, train

    demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
    cfg = load_config("PushT", "quick", out_dir=str(tmp_path), steps=2, warmup_steps=0, batch_size=4,
                      model={"width": 48, "layers": 1, "heads": 2})
    policy = Policy.from_checkpoint(train(cfg, demos)["checkpoint"])
    out = audit_checkpoint(policy, demos, samples=100)
    views = out["views"]
    assert out["primary"] == "c_t" and list(views) == ["c_t", "e_rgb", "z_hat"]
    assert views["c_t"]["dim"] == 48 and views["e_rgb"]["dim"] == views["z_hat"]["dim"] == 64
    with torch.inference_mode():   # c_t is what the memory embeds: the encoder's output for the newest frame
        obs = WindowDataset.from_demos(demos)[np.arange(3)]["obs"]
        reps = policy.model.representations(obs)
        c, _ = policy.model._encode(obs)
    assert torch.equal(reps["c_t"], c[:, -1].float())


@pytest.fixture(scope="module")
def tiny_policy(pusht_demo_file, tmp_path_factory):
    from jepa_envs.datasets.hdf5 import load_dataset
    from jepa_policy.detectors import fit_detectors
    from jepa_policy.policy import Policy
    from jepa_policy.train import load_config, train

    demos = load_dataset(pusht_demo_file, task="PushT", image_size=32)
    cfg = load_config("PushT", "quick", out_dir=str(tmp_path_factory.mktemp("vis")), steps=2, warmup_steps=0,
                      batch_size=4, model={"width": 48, "layers": 1, "heads": 2})
    checkpoint = train(cfg, demos)["checkpoint"]
    fit_detectors(Policy.from_checkpoint(checkpoint, detectors=False), checkpoint, demos, samples=256)
    policy = Policy.from_checkpoint(checkpoint, detectors=True)   # RND, PCA-kmeans, Mahalanobis beside z_hat
    return policy, demos, checkpoint, pusht_demo_file


def test_visibility_audit_agrees_with_a_window_by_window_recompute(tiny_policy):
    """The batched audit equals d_NMSE computed one window at a time from the fault's own frames (fault_frames,
    the window's seed): the change of the realized latent, the straddling and inside NMSE, and their rates."""
    from jepa_envs.tasks.fault_replay import fault_frames
    from jepa_policy.audit import visibility_audit

    policy, demos, _, _ = tiny_policy
    model, spec, seed, n = policy.model, policy.spec, 4, 12
    out = visibility_audit(policy, demos, faults=["camera_shift", {"name": "colour_shift", "brightness": 0.5,
                                                                    "label": "dark"}], samples=n, seed=seed,
                           batch_size=5)
    assert list(out["faults"]) == ["camera_shift", "dark"] and out["samples"] == n
    windows = WindowDataset.from_demos(demos)
    idx = manifest(len(windows), n, seed)
    keys = spec.image_keys
    for label, name, options in (("camera_shift", "camera_shift", {}), ("dark", "colour_shift", {"brightness": 0.5})):
        clean_err, persistence, enc, straddle, inside = [], [], [], [], []
        embed_clean, embed_fault = [], []
        for w in idx:
            batch = windows[np.array([w])]
            obs, fut = batch["obs"], batch["future_obs"]
            frames = [{k: obs[k][0, j].numpy() for k in keys} for j in range(obs[keys[0]].shape[1])]
            shown = fault_frames(spec, [*frames, {k: fut[k][0].numpy() for k in keys}], name,
                                 seed * 1_000_003 + int(w), **options)
            f_obs = {**obs, **{k: torch.from_numpy(np.stack([f[k] for f in shown[:-1]]))[None] for k in keys}}
            f_fut = {k: torch.from_numpy(shown[-1][k])[None] for k in keys}
            with torch.inference_mode():
                _, z_hat, c = model.predict_embedded(obs)
                z = model.encode_future(fut).double().numpy()
                z_now = model.encode_future({k: obs[k][:, -1] for k in keys}).double().numpy()
                _, zf_hat, cf = model.predict_embedded(f_obs)
                zf = model.encode_future(f_fut).double().numpy()
            z_hat, zf_hat = z_hat.double().numpy(), zf_hat.double().numpy()
            embed_clean.append(policy.detectors.score(c.numpy()))
            embed_fault.append(policy.detectors.score(cf.numpy()))
            persistence.append(nmse_rows(z_now, z)[0])
            clean_err.append(nmse_rows(z_hat, z)[0])
            enc.append(nmse_rows(z, zf)[0])
            straddle.append(nmse_rows(z_hat, zf)[0])
            inside.append(nmse_rows(zf_hat, zf)[0])
        clean_err, persistence, enc, straddle, inside = map(np.array, (clean_err, persistence, enc, straddle, inside))
        row = out["faults"][label]
        assert row["encoder_median"] == pytest.approx(np.median(enc), rel=1e-5)
        assert row["encoder_vs_persistence"] == pytest.approx(np.median(enc / persistence), rel=1e-5)
        assert row["fault"]["name"] == name
        views = [("straddle", straddle, clean_err), ("inside", inside, clean_err)]
        for score in ("rnd", "pca_kmeans", "mahalanobis"):
            views.append((score, np.array([float(e[score][0]) for e in embed_fault]),
                          np.array([float(e[score][0]) for e in embed_clean])))
        for view, values, clean in views:
            ratio = np.median(values / np.maximum(np.abs(clean), 1e-12))
            assert row[view]["median_ratio"] == pytest.approx(ratio, rel=1e-4), view
            # near-ties between a faulted value and a clean quantile must not decide: compare with a margin
            for level, q in (("exceed_decision", 0.9), ("exceed_ten_decisions", 0.99)):
                t = np.quantile(clean, q)
                assert np.mean(values > t * (1 + 1e-5)) <= row[view][level] <= np.mean(values > t * (1 - 1e-5)), \
                    (view, level)
    assert out["clean"]["nmse"]["median"] == pytest.approx(np.median(clean_err), rel=1e-5)
    assert out["clean"]["persistence"]["median"] == pytest.approx(np.median(persistence), rel=1e-5)
    assert out["levels"] == {"exceed_decision": 0.9, "exceed_ten_decisions": pytest.approx(0.99)}
    for level, q in (("exceed_decision", 0.9), ("exceed_ten_decisions", 0.99)):
        assert out["clean"]["nmse"]["quantiles"][level] == pytest.approx(np.quantile(clean_err, q), rel=1e-5)


def test_a_change_the_encoder_cannot_see_sits_at_the_clean_rates(tiny_policy):
    """A colour 'shift' of gain 1 changes no pixel: the latent does not move, every ratio is 1 and every exceed
    rate is the clean windows' own rate above their quantile (about alpha); a real darkening moves the latent."""
    from jepa_policy.audit import visibility_audit

    policy, demos, _, _ = tiny_policy
    out = visibility_audit(policy, demos, samples=40, faults=[
        {"name": "colour_shift", "brightness": 1.0, "gains": [1, 1, 1], "label": "none"},
        {"name": "colour_shift", "brightness": 0.3, "label": "dark"}])
    none, dark = out["faults"]["none"], out["faults"]["dark"]
    assert none["encoder_median"] == 0.0 and none["encoder_vs_persistence"] == 0.0
    for view in ("straddle", "inside"):
        assert none[view]["median_ratio"] == pytest.approx(1.0, abs=1e-6)
        assert 0.05 <= none[view]["exceed_decision"] <= 0.1 and none[view]["exceed_ten_decisions"] <= 0.025
    assert dark["encoder_median"] > 0 and dark["straddle"]["median_ratio"] != pytest.approx(1.0, abs=1e-3)


def test_the_visibility_audit_refuses_what_it_cannot_measure(tiny_policy, capsys):
    from jepa_policy.audit import visibility_audit
    from jepa_policy.cli import main

    policy, demos, checkpoint, demo_file = tiny_policy
    with pytest.raises(ValueError, match=r"\['block_displaced'\] is not one .*jepa-policy eval --faults"):
        visibility_audit(policy, demos, faults=["camera_shift", "block_displaced"], samples=4)
    with pytest.raises(ValueError, match="share a label"):
        visibility_audit(policy, demos, faults=["camera_shift", {"name": "camera_shift"}], samples=4)
    with pytest.raises(ValueError, match="camera shift must be >= 1 pixel"):
        visibility_audit(policy, demos, faults=[{"name": "camera_shift", "pixels": 0}], samples=4)
    with pytest.raises(ValueError, match="alpha must lie in"):
        visibility_audit(policy, demos, samples=4, alpha=1.5)
    base = ["audit", "--checkpoint", str(checkpoint), "--dataset", str(demo_file), "--kind", "visibility",
            "--no-progress", "--samples", "6"]
    assert main([*base, "--faults", "action_latency"]) != 0
    err = capsys.readouterr().err
    assert "action_latency" in err and "eval --faults" in err and "Traceback" not in err
    for bad, says in ((["--faults", "camera_shift:onset=5"], "drop onset="), (["--faults", ";"], "names no fault"),
                      (["--samples", "0"], "--samples must be >= 1"), (["--seed", "-1"], "--seed must be >= 0")):
        assert main([*base, *bad]) != 0, bad
        err = capsys.readouterr().err
        assert says in err and "Traceback" not in err, (bad, err)
    assert main(["audit", "--checkpoint", str(checkpoint), "--dataset", str(demo_file), "--kind", "collapse",
                 "--faults", "camera_shift"]) != 0
    assert "add --kind visibility" in capsys.readouterr().err
    assert main([*base, "--faults", "camera_shift;camera_shift:pixels=5,label=camera_5px"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["dataset"] == str(demo_file)
    report = printed["visibility"]
    assert list(report["faults"]) == ["camera_shift", "camera_5px"] and report["samples"] == 6
    assert report["faults"]["camera_5px"]["fault"] == {"name": "camera_shift", "pixels": 5, "label": "camera_5px"}
    assert main([*base[:-2]]) == 0   # no --faults: every image fault of the task
    assert set(json.loads(capsys.readouterr().out)["visibility"]["faults"]) == {
        "background_tint", "camera_shift", "colour_shift", "distractors", "sensor_noise"}
