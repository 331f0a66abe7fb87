"""docs/serving.md's robot loop, run as written with the published openpi-client (WebsocketClientPolicy +
ActionChunkBroker, in the numpy < 2 venv that scripts/interop.sh builds), against a real server: every action equals
the same checkpoint's in-process ``Policy.act`` bit for bit, across two episodes. Skipped where that venv is not
built (`make interop` builds it, then runs the same check on whole episodes)."""
from __future__ import annotations

from pathlib import Path

import pytest
from _serve_helpers import checkpoint, serve  # noqa: F401 (fixtures)
from script_loader import load_script

from jepa_policy.policy import Policy

ROOT = Path(__file__).resolve().parents[2]
OPENPI_PYTHON = ROOT / ".cache" / "interop" / "openpi" / "bin" / "python"

pytestmark = [pytest.mark.timeout(300),
              pytest.mark.skipif(not OPENPI_PYTHON.exists(),
                                 reason="the openpi-client venv is not built (make interop)")]


def _interop_openpi():
    return load_script("interop_openpi")


def test_the_documented_openpi_loop_equals_in_process_act(serve, checkpoint):
    server = serve(api_key="doc-key")
    result = _interop_openpi().drive_documented_loop(str(OPENPI_PYTHON), server.port, "doc-key",
                                                      Policy.from_checkpoint(checkpoint), episodes=2, max_steps=30)
    assert result["steps"] == 60 and result["metadata"]["task"] == "PushT"
    assert result["bit_equal"], f"max |served - in-process| = {result['max_abs_action_diff']}"
