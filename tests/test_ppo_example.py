"""experiments/ppo_rejax.py without the rl extra (rejax, gymnax): --help works and a run says
in one line how to install them. With the extra, tests/test_navigation.py trains it."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).parents[1] / "experiments" / "ppo_rejax.py"


def test_the_ppo_example_explains_itself_without_the_rl_extra():
    helped = subprocess.run([sys.executable, str(SCRIPT), "--help"], capture_output=True,
                            text=True, timeout=300)
    assert helped.returncode == 0, helped.stderr
    assert helped.stdout.startswith("usage: ppo_rejax.py") and "--timesteps" in helped.stdout
    if importlib.util.find_spec("rejax") is not None:
        return                      # with the extra installed a run would train
    refused = subprocess.run([sys.executable, str(SCRIPT), "--timesteps", "1"],
                             capture_output=True, text=True, timeout=300)
    assert refused.returncode == 1
    assert refused.stderr.strip().splitlines() == [
        "error: experiments/ppo_rejax.py needs rejax and gymnax, the rl extra: "
        'pip install ".[rl]" (from the checkout)']
