"""``jepa-policy eval --faults``: every fault's name, options and label are checked before the first rollout.
Before, ``--faults "sensor_noise;bogus"`` rolled out the whole natural block and sensor_noise's episodes, then
failed on 'bogus' and wrote no records (2 episodes: 28 s against 16 s to fail; a study's 320: minutes lost), and
``label=natural`` under --faults-only tagged faulted episodes as natural ones (compare then fits and scores them as
natural failures and successes)."""
import pytest

from _serve_helpers import checkpoint  # noqa: F401 (the policy-server tests' small checkpoint, trained once)
from jepa_policy.cli import _fault_spec, main


@pytest.mark.parametrize("faults, error", [
    ("sensor_noise;bogus", "unknown fault 'bogus'"),
    ("sensor_noise;sensor_noise:std=-1,label=loud", "sensor noise std must be in (0, 64]"),
    ("sensor_noise;action_noise:stdd=3", "unexpected keyword argument 'stdd'"),
    (" ; ;", "names no fault"),   # was: the natural block alone (with --faults-only: an empty records file, rc 0)
])
def test_a_bad_fault_is_refused_before_any_episode_runs(checkpoint, tmp_path, capsys, faults, error):
    out = tmp_path / "records.jsonl"
    assert main(["eval", "--checkpoint", str(checkpoint), "--episodes", "2", "--max-steps", "10", "--workers", "0",
                 "--faults", faults, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert error in err and "[eval]" not in err   # no regime was rolled out before the refusal
    assert not out.exists()


@pytest.mark.parametrize("label", ["natural", "", "a|b", "tint faint", "x" * 65])
def test_a_label_must_be_a_plain_regime_name_other_than_natural(label):
    with pytest.raises(ValueError, match="fault label .* must be 1-64 letters, digits or _ . : - and not 'natural'"):
        _fault_spec(f"sensor_noise:std=9,label={label}")
    assert _fault_spec("sensor_noise:std=9,label=noisy_v2.1")["label"] == "noisy_v2.1"
