"""robosuite imports quietly: scripts/setup.sh runs robosuite's own setup_macros (its documented fix), so the three
"No private macro file found!" warnings no longer open every command that builds a robosuite task."""
import importlib.util
import subprocess
import sys

import pytest

pytestmark = pytest.mark.robosuite


@pytest.mark.skipif(importlib.util.find_spec("robosuite") is None, reason="robosuite is not installed")
def test_robosuite_imports_without_the_private_macro_warning():
    done = subprocess.run([sys.executable, "-c", "import robosuite"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "No private macro file found" not in done.stdout + done.stderr, (
        "robosuite has no macros_private.py: run bash scripts/setup.sh (it runs python -m "
        "robosuite.scripts.setup_macros)")
