"""``jepa-monitor compare`` cross-fits: no episode may be scored by a model (stack) or judged by a calibration
fitted on it. One seed's natural record loaded twice (a re-roll beside the main job's records, the same
checkpoint) put the two copies in different folds, so each copy was fitted on while its twin was scored: a stack
of pure-noise signals ranked failures at a mean AUROC of 0.64 over 15 draws instead of 0.50. Copies now share a
fold; with unique seeds the folds are unchanged."""
import numpy as np

from monitor_service.offline import compare


def record(seed, success, values):
    decisions = [{"step": 8 * j, "target_step": 8 * j + 4, "nmse": float(values[0][j]),
                  "scores": {f"s{k}": float(values[k][j]) for k in range(1, len(values))}}
                 for j in range(values.shape[1])]
    return {"seed": seed, "success": success, "length": 80, "decisions": decisions, "arm": "jepa", "checkpoint": "c"}


def noise_episodes(rng, copies):
    rows = []
    for seed in range(40):
        success, values = bool(rng.random() < 0.5), np.exp(rng.normal(size=(8, 10)))
        rows += [record(seed, success, values)] * copies
    return [compare.episode_of(r) for r in rows]


def test_copies_of_a_seed_share_a_fold_and_a_noise_stack_stays_at_chance():
    aurocs = []
    for rep in range(10):
        once, twice = noise_episodes(np.random.default_rng(rep), 1), noise_episodes(np.random.default_rng(rep), 2)
        compare.assign_folds(once, 5, rep)
        compare.assign_folds(twice, 5, rep)
        assert [e.fold for e in twice] == [e.fold for e in once for _ in range(2)]   # same folds, twins together
        members = compare.stack_members(sorted(twice[0].values))
        stacked = compare.stacked_scores(twice, members, 10)
        for i, e in enumerate(twice):   # the episode's twin was not in its fit: scored as its twin is
            assert stacked[i] == stacked[i ^ 1]
        row = compare.ranking(twice, members, "natural", 10, 50, 0, stacked=(members, stacked))["stack"]
        aurocs.append(row["auroc"])
    assert np.mean(aurocs) < 0.58, aurocs   # leaking: 0.64 on these draws; honest: 0.50 +- 0.03


def test_a_score_whose_episode_mean_overflows_leaves_the_stack_standing():
    """Scores up to 1.7e308 are valid (the service accepts them); ten of 1e308 average to inf, whose log made
    the standardised features NaN, and the whole compare died in sklearn ('Input X contains NaN')."""
    rng = np.random.default_rng(3)
    rows = [record(seed, seed % 2 == 0, np.exp(rng.normal(size=(3, 10)))) for seed in range(20)]
    for d in rows[7]["decisions"]:
        d["scores"]["s1"] = 1e308
    episodes = [compare.episode_of(r) for r in rows]
    result = compare.compare(episodes, n_bootstrap=50, rule_names=("default",), views=("whole",))
    row = result["groups"]["jepa:c"]["views"]["whole"]["ranking"]["natural"]["stack"]
    assert row["failures"] + row["successes"] == 19 and row["auroc"] is not None   # only the overflowing one out
    assert "stack" in compare.markdown(result)


def test_a_checkpoints_folds_do_not_depend_on_the_other_checkpoints_loaded_beside_it():
    """The folds (and so the stack) of one group are the same whether it is compared alone or beside others."""
    from monitor_service.offline.compare import Episode, assign_folds

    def group(name, n):
        rng = np.random.default_rng(len(name))
        return [Episode(s, bool(rng.random() < 0.5), 100, "natural", name, np.arange(3), {}, {}, None)
                for s in range(n)]

    alone = group("mip:b.pt", 40)
    assign_folds(alone, 5)
    beside = group("jepa:a.pt", 33) + group("mip:b.pt", 40)
    assign_folds(beside, 5)
    assert [e.fold for e in alone] == [e.fold for e in beside if e.group == "mip:b.pt"]
