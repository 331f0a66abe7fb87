"""A checkpoint is data: every command that loads one refuses a file whose pickle would run code, and says so in
one line. The crafted file runs ``touch MARKER`` when unpickled the unsafe way; the marker must never appear."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from jepa_policy.checkpoint import FORMAT, UnsafeCheckpoint, load_checkpoint
from jepa_policy.cli import main


class _RunsCode:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture(scope="module")
def crafted(tmp_path_factory):
    """(crafted checkpoint, crafted encoder weights, the marker their pickles would create)."""
    root = tmp_path_factory.mktemp("crafted")
    marker = root / "code-ran"
    checkpoint = root / "crafted.pt"
    torch.save({"format": FORMAT, "step": 4, "model_config": {}, "ema": _RunsCode(marker)}, checkpoint)
    weights = root / "weights.pt"
    torch.save({"state_dict": {"encoder.cameras.top_image.conv1.weight": _RunsCode(marker)}}, weights)
    return checkpoint, weights, marker


@pytest.fixture(scope="module")
def trained(tmp_path_factory, pusht_demo_file):
    out = tmp_path_factory.mktemp("run")
    assert main(["train", "--task", "PushT", "--preset", "quick", "--dataset", str(pusht_demo_file), "--steps", "2",
                 "--warmup-steps", "1", "--eval-every", "0", "--out", str(out), "--no-progress"]) == 0
    return out / "checkpoints" / "latest.pt"


def _refused(capsys, marker: Path, rc: int) -> str:
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "refused" in err and "could run code" in err and len(err.strip().splitlines()) == 1, err
    assert not marker.exists(), "the crafted pickle ran"
    return err


def test_a_checkpoint_written_by_train_loads_as_data(trained):
    ckpt = load_checkpoint(trained)
    assert ckpt["format"] == FORMAT and ckpt["step"] == 2
    assert isinstance(ckpt["rng"]["numpy"][1], np.ndarray)   # numeric arrays are allowed, as data


def test_object_arrays_are_refused_too(tmp_path):
    path = tmp_path / "objects.pt"
    torch.save({"format": FORMAT, "stats": np.array([1, "x"], dtype=object)}, path)
    with pytest.raises(UnsafeCheckpoint, match="ObjectDType"):
        load_checkpoint(path)


@pytest.mark.parametrize("command", [
    ["eval", "--checkpoint", "{ckpt}", "--episodes", "1"],
    ["audit", "--checkpoint", "{ckpt}", "--dataset", "{demos}"],
    ["protocols", "{ckpt}"],
    ["robot", "--checkpoint", "{ckpt}", "--address", "tcp://127.0.0.1:9", "--episodes", "1", "--no-wait"],
    ["train", "--task", "PushT", "--preset", "quick", "--dataset", "{demos}", "--resume", "{ckpt}",
     "--out", "{tmp}/resumed", "--no-progress"],
    ["train", "--task", "PushT", "--preset", "quick", "--dataset", "{demos}", "--model",
     '{{"encoder_weights": "{weights}"}}', "--steps", "2", "--out", "{tmp}/encoder", "--no-progress"],
    ["serve", "--checkpoint", "{ckpt}", "--port", "0"],
], ids=["eval", "audit", "protocols", "robot", "train-resume", "train-encoder-weights", "serve"])
def test_every_command_refuses_a_crafted_file(command, crafted, pusht_demo_file, tmp_path, capsys):
    ckpt, weights, marker = crafted
    argv = [a.format(ckpt=ckpt, weights=weights, demos=pusht_demo_file, tmp=tmp_path) for a in command]
    _refused(capsys, marker, main(argv))


def test_the_demo_refuses_a_crafted_checkpoint_it_would_reuse(crafted, pusht_demo_file, tmp_path, capsys):
    """jepa-demo reuses a finished run's latest.pt when its stamp matches: a file swapped in is refused unread."""
    from jepa_policy.demo.job import MODES, _file_digest, load_config, train_arm

    checkpoint, _, marker = crafted
    cfg = MODES["quick"]
    run_dir = tmp_path / "runs" / "jepa_seed0"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "latest.pt").write_bytes(checkpoint.read_bytes())
    tcfg = load_config("PushT", cfg.preset, **dict(cfg.train_overrides, arm="jepa", seed=0,
                                                    dataset=str(pusht_demo_file), out_dir=str(run_dir)))
    (run_dir / "demo_config.json").write_text(json.dumps({"train": tcfg.to_dict(),
                                                          "dataset_digest": _file_digest(pusht_demo_file)}))
    with pytest.raises(UnsafeCheckpoint, match="could run code"):
        train_arm(cfg, "jepa", 0, pusht_demo_file, tmp_path, fresh=False)
    assert not marker.exists()


def test_the_console_script_prints_one_line_and_no_traceback(crafted):
    ckpt, _, marker = crafted
    out = subprocess.run([sys.executable, "-m", "jepa_policy.cli", "eval", "--checkpoint", str(ckpt)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr and "refused" in out.stderr
    assert not marker.exists()
