"""``jepa-monitor ceiling`` (monitor_service/offline/outcome_ceiling.py): the AUROC over pairs of different seeds
against a brute-force reference; the ceiling estimates on draws from a known distribution of per-seed failure
probabilities against its exact ceiling; draws whose prefixes differ refused with the fix; the command end to end
on record files."""
from __future__ import annotations

import json

import numpy as np
import pytest

from monitor_service.offline import outcome_ceiling as cl
from monitor_service.cli import main
from monitor_service.offline.compare import episode_of

PREFIX = 10


def _brute(scores, labels, clusters):
    num = den = 0.0
    for i in np.flatnonzero(labels == 1):
        for j in np.flatnonzero(labels == 0):
            if clusters[i] != clusters[j]:
                den += 1
                num += 1.0 if scores[i] > scores[j] else 0.5 if scores[i] == scores[j] else 0.0
    return num / den


def test_cross_cluster_auroc_equals_the_pairwise_count():
    rng = np.random.default_rng(0)
    for _ in range(5):
        n = 60
        clusters = rng.integers(0, 12, n)
        labels = rng.integers(0, 2, n)
        scores = rng.integers(0, 6, n).astype(float)     # many ties, within and across clusters
        assert cl.cross_cluster_auroc(scores, labels, clusters) == pytest.approx(_brute(scores, labels, clusters))
    assert cl.cross_cluster_auroc(np.ones(3), np.ones(3, int), np.arange(3)) is None


def _record(seed, regime, success, signal, rng, diverge=False):
    """An episode of 12 decisions; its prefix values are a function of the seed alone (``diverge``: not)."""
    prefix_rng = np.random.default_rng([seed, 7])
    decisions = []
    for j in range(12):
        v = float(signal + 0.1 * prefix_rng.random()) if j < PREFIX else float(rng.random())
        if diverge and j == 3:
            v += 1.0
        decisions.append({"step": 8 * j, "target_step": 8 * j + 4, "nmse": v, "nmse_persistence": 1.0,
                          "scores": {"stac": float(prefix_rng.random()) if j < PREFIX else float(rng.random())}})
    return {"seed": seed, "success": bool(success), "length": 300 if not success else 120, "regime": regime,
            "arm": "jepa", "checkpoint": "ck", "decisions": decisions,
            **({} if regime == "natural" else {"fault": "sensor_noise", "fault_onset": 80})}


def _population(seeds, draws, rng, p_of):
    """Every seed's ``draws`` outcomes drawn with its failure probability p_of(seed); nmse's prefix tracks p."""
    rows = []
    for seed in range(seeds):
        p = p_of(seed)
        for r in range(draws):
            rows.append(_record(seed, "natural" if r == 0 else f"draw{r}", rng.random() >= p, p, rng))
    return rows


def test_the_ceiling_of_a_known_distribution_is_bracketed_and_signals_are_scored_on_the_same_pairs():
    """Each seed fails with its own p ~ U(0, 1): the exact ceiling (a score knowing p) is P(p of a failure > p of a
    success) = int int_{x > y} 2x 2(1 - y) = 5/6. With 8 draws per seed the leave-one-out estimate sits below the
    ceiling realised on these very draws (p itself as the score) and the plug-in above it (measured: about 0.04
    each way); nmse (p plus a little noise in the prefix) is a score of the prefix and stays under the plug-in;
    stac (noise) and the chance row sit at 0.5."""
    rng = np.random.default_rng(1)
    p = rng.random(400)
    rows = _population(400, 8, rng, lambda s: p[s])
    result = cl.ceiling([episode_of(r) for r in rows], prefix=PREFIX, n_bootstrap=200)
    g = result["groups"]["jepa:ck"]
    assert g["seeds"] == 400 and g["draws"] == 3200 and g["draws_per_seed"] == [8, 8]
    y = np.array([0 if r["success"] else 1 for r in rows])
    seeds = np.array([r["seed"] for r in rows])
    realised = cl.cross_cluster_auroc(p[seeds], y, seeds)
    assert abs(realised - 5 / 6) < 0.03
    loo, plug = g["ceiling"]["leave_one_out"], g["ceiling"]["plug_in"]
    assert realised - 0.08 < loo["auroc"] < realised - 0.01 and realised + 0.01 < plug["auroc"] < realised + 0.08
    assert loo["ci"][0] < loo["auroc"] < loo["ci"][1] and plug["ci"][0] < plug["auroc"] < plug["ci"][1]
    assert realised - 0.05 < g["signals"]["nmse"]["auroc"] <= plug["auroc"]
    assert abs(g["signals"]["stac"]["auroc"] - 0.5) < 0.05 and abs(g["signals"]["random"]["auroc"] - 0.5) < 0.05
    mixed = np.mean([0 < sum(not r["success"] for r in rows[8 * s: 8 * s + 8]) < 8 for s in range(400)])
    assert g["seeds_mixed_fraction"] == pytest.approx(mixed)


def test_a_determined_outcome_has_a_ceiling_of_one():
    rng = np.random.default_rng(2)
    g = cl.ceiling([episode_of(r) for r in _population(60, 3, rng, lambda s: float(s % 2))], prefix=PREFIX,
                   n_bootstrap=50)["groups"]["jepa:ck"]
    assert g["seeds_mixed"] == 0
    assert g["ceiling"]["plug_in"]["auroc"] == 1.0 and g["ceiling"]["leave_one_out"]["auroc"] == 1.0


def test_draws_that_differ_within_the_prefix_are_refused_with_the_fix():
    rng = np.random.default_rng(3)
    rows = _population(20, 2, rng, lambda s: 0.5)
    rows[7] = _record(rows[7]["seed"], rows[7]["regime"], rows[7]["success"], 0.5, rng, diverge=True)
    with pytest.raises(ValueError, match=r"seed 3: draws 'natural' and 'draw1' differ in the first 10 decisions "
                                         r"\(signal 'nmse'\).*its onset \(80\) is already after them.*--workers 0"):
        cl.ceiling([episode_of(r) for r in rows], prefix=PREFIX, n_bootstrap=0)
    rows[7]["fault_onset"] = 16                                      # a perturbation that starts inside the prefix
    with pytest.raises(ValueError, match=r"seed 3: .*start its perturbation after them, e.g. "
                                         r"sensor_noise:onset=80,draw=1 \(onset of this one: 16\)"):
        cl.ceiling([episode_of(r) for r in rows], prefix=PREFIX, n_bootstrap=0)
    twice = _population(4, 2, rng, lambda s: 0.5) + [_record(0, "draw1", True, 0.5, rng)]
    with pytest.raises(ValueError, match="two records of regime 'draw1'.*label=draw2"):
        cl.ceiling([episode_of(r) for r in twice], prefix=PREFIX, n_bootstrap=0)
    with pytest.raises(ValueError, match="no seed has two or more draws"):
        cl.ceiling([episode_of(r) for r in _population(5, 1, rng, lambda s: 0.5)], prefix=PREFIX, n_bootstrap=0)


def test_the_command_reads_record_files_and_writes_its_figures(tmp_path, capsys):
    rng = np.random.default_rng(4)
    rows = _population(80, 4, rng, lambda s: 0.2 if s % 2 else 0.8)
    natural, draws = tmp_path / "natural.jsonl", tmp_path / "draws.jsonl"
    natural.write_text("".join(json.dumps(r) + "\n" for r in rows if r["regime"] == "natural"))
    draws.write_text("".join(json.dumps(r) + "\n" for r in rows if r["regime"] != "natural"))
    out = tmp_path / "ceiling.json"
    assert main(["ceiling", str(natural), str(draws), "--bootstrap", "100", "--out", str(out)]) == 0
    text, err = capsys.readouterr()
    assert "ceiling: " in err and "row" in err        # its bootstrapped rows on a bar
    assert "80 seeds reaching 10 decisions, 320 draws" in text and "leave-one-out" in text and "stack" in text
    saved = json.loads(out.read_text())["groups"]["jepa:ck"]
    assert saved["ceiling"]["leave_one_out"]["auroc"] < saved["ceiling"]["plug_in"]["auroc"]
    assert saved["signals"]["stack"]["members"] == ["nmse", "nmse_ratio", "stac"]
    assert main(["ceiling", str(natural), "--prefix", "0"]) == 2
    assert "--prefix must be >= 1" in capsys.readouterr().err


def test_infinite_scores_tie_within_a_seed_as_the_ranks_do():
    """inf - inf is NaN: a within-seed pair of two infinite scores is a tie (1/2), as in the ranks it is taken from."""
    inf = np.inf
    scores, labels, clusters = np.array([inf, inf, 0.0, 1.0]), np.array([1, 0, 1, 0]), np.array([0, 0, 1, 2])
    assert cl.cross_cluster_auroc(scores, labels, clusters) == pytest.approx(_brute(scores, labels, clusters))


def _files(tmp_path, rows, name="records.jsonl"):
    path = tmp_path / name
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return str(path)


def test_what_the_command_leaves_out_it_says_and_what_it_cannot_use_it_refuses(tmp_path, capsys):
    rng = np.random.default_rng(5)
    rows = _population(30, 3, rng, lambda s: 0.5) + [_record(100 + s, "natural", s % 2, 0.5, rng) for s in range(4)]
    rows[0]["decisions"][0]["scores"]["rnd"] = 0.3                      # one seed's first draw carries one more signal
    path = _files(tmp_path, rows)
    assert main(["ceiling", path, "--bootstrap", "0"]) == 0
    out = capsys.readouterr().out
    assert "note: jepa:ck: 4 seeds left out: one draw each" in out
    assert "note: jepa:ck: rnd left out for 29 of 30 seeds" in out
    assert main(["ceiling", path, "--signals", "nmse,nosuch", "--bootstrap", "0"]) == 2
    assert "no record carries 'nosuch'; the records carry" in capsys.readouterr().err
    draws_only = _files(tmp_path, [r for r in rows if r["regime"] != "natural"], "draws.jsonl")
    assert main(["ceiling", draws_only, "--bootstrap", "0"]) == 0
    assert "no stack row: it is fitted on the natural run of every seed" in capsys.readouterr().out
    every = _files(tmp_path, _population(10, 2, rng, lambda s: 0.0), "all_succeed.jsonl")
    assert main(["ceiling", every, "--bootstrap", "0"]) == 2
    assert "all 20 draws succeeded; an AUROC needs both failures and successes" in capsys.readouterr().err
    assert main(["ceiling", path, "--prefix", "50", "--bootstrap", "0"]) == 2
    assert "no episode reaches 50 decisions (the longest has 12): use --prefix 12" in capsys.readouterr().err
    for bad, why in ((["--bootstrap", "10"], "--bootstrap must be 0 (no intervals) or >= 100"),
                     (["--out", str(tmp_path / "x.json" / "y.json")], "give a file in an existing folder"),
                     (["--out", str(tmp_path / "ceiling.txt")], "name a .json file")):
        assert main(["ceiling", path, *bad]) == 2
        assert why in capsys.readouterr().err


def test_repeating_a_where_key_keeps_either_value(tmp_path, capsys):
    rng = np.random.default_rng(6)
    rows = _population(20, 2, rng, lambda s: 0.5)
    for seed in range(20):                          # another fault of the same file, its onset inside the prefix
        rows.append(_record(seed, "block_displaced", seed % 2, 0.5, rng, diverge=True) | {"fault_onset": 30})
    path = _files(tmp_path, rows)
    assert main(["ceiling", path, "--bootstrap", "0"]) == 2
    assert "draws 'natural' and 'block_displaced' differ" in capsys.readouterr().err
    for r in rows:
        if r["regime"] == "natural":
            del r["regime"]                         # jepa-policy eval without --faults writes no regime: natural
    path = _files(tmp_path, rows)
    assert main(["ceiling", path, "--where", "regime=natural", "--where", "regime=draw1", "--bootstrap", "0"]) == 0
    assert "20 seeds reaching 10 decisions, 40 draws" in capsys.readouterr().out


@pytest.mark.parametrize("mangle, why", [
    (lambda r: r.update(success="false"), "success must be true or false, got 'false'"),
    (lambda r: r.update(success=None), "success must be true or false, got None"),
    (lambda r: r["decisions"][2]["scores"].update(stac=[1, 2]), "a decision's 'stac' is malformed"),
    (lambda r: r["decisions"][2].update(scores=[1, 2]), "a decision's 'scores' is malformed"),
    (lambda r: r["decisions"][2].update(target_step=None), "a decision's 'target_step' is malformed"),
    (lambda r: r["decisions"][2]["scores"].update(stac="abc"), "a decision's 'stac' is malformed"),
])
def test_a_malformed_record_is_refused_naming_its_line_and_field(tmp_path, capsys, mangle, why):
    rng = np.random.default_rng(7)
    rows = _population(4, 2, rng, lambda s: 0.5)
    mangle(rows[3])
    path = _files(tmp_path, rows)
    assert main(["ceiling", path, "--bootstrap", "0"]) == 2
    err = capsys.readouterr().err
    assert f"{path}:4: " in err and why in err and "Traceback" not in err


def test_a_cut_or_mislabelled_gzip_file_is_refused_with_the_fix(tmp_path, capsys):
    import gzip
    rng = np.random.default_rng(8)
    blob = gzip.compress("".join(json.dumps(r) + "\n" for r in _population(10, 2, rng, lambda s: 0.5)).encode())
    cut, plain = tmp_path / "cut.jsonl.gz", tmp_path / "plain.jsonl.gz"
    cut.write_bytes(blob[: len(blob) // 2])
    plain.write_text("{}\n")
    for path in (cut, plain):
        assert main(["ceiling", str(path), "--bootstrap", "0"]) == 2
        assert "not a complete gzip file" in capsys.readouterr().err


def test_records_that_name_no_checkpoint_are_not_pooled_across_files(tmp_path, capsys):
    """Two files of records without arm or checkpoint (as jepa-policy eval wrote them without --faults before it
    named them) may come from two checkpoints: reading them as one policy would pool their raw scores."""
    rng = np.random.default_rng(9)
    rows = _population(6, 2, rng, lambda s: 0.5)
    for r in rows:
        del r["arm"], r["checkpoint"]
    a = _files(tmp_path, rows[::2], "a.jsonl")
    b = _files(tmp_path, rows[1::2], "b.jsonl")
    assert main(["compare", a, b]) == 2
    err = capsys.readouterr().err
    assert "name no checkpoint, so they would be pooled as one policy" in err and "a.jsonl" in err
