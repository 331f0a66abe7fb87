"""The episode bar of eval and protocols --select counts finished episodes from the pool's resets."""
import io

from tqdm import tqdm

from jepa_policy.progress import EpisodeProgress


class _Pool:
    num_envs = 2

    def __init__(self):
        self.resets = []

    def reset(self, seeds, active=None):
        self.resets.append((list(seeds), active))
        return "obs", {}


def test_each_round_counts_when_the_next_starts_a_rerun_once_and_the_last_at_finish():
    with tqdm(total=7, file=io.StringIO()) as bar:
        pool = _Pool()
        seen = EpisodeProgress(pool, bar)
        assert seen.reset([0, 1], active=[True, True]) == ("obs", {}) and bar.n == 0
        seen.reset([2, 3], active=[True, True])
        seen.reset([2, 3], active=[True, True])        # a worker died: the round is rerun, counted once
        seen.reset([4, 5], active=[True, False])       # the last round's spare is never stepped
        assert bar.n == 4
        seen.finish()
        assert bar.n == 5
        seen.reset([0, 1])                             # the other candidate on the same seeds: a new evaluation
        seen.finish()
        assert bar.n == 7
        assert seen.num_envs == 2 and len(pool.resets) == 5    # the rest is the pool's own
