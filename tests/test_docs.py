"""The documentation: an API reference built from the docstrings, and the README's quick start
run as the README writes it."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).parents[1]


def test_the_api_reference_builds_from_the_docstrings(tmp_path):
    subprocess.run([sys.executable, "-m", "pdoc", "-o", str(tmp_path), "gst_jax"], check=True,
                   capture_output=True)
    pages = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*.html")}
    assert {"gst_jax.html", "gst_jax/crowdnav.html", "gst_jax/predict.html",
            "gst_jax/config.html", "gst_jax/runs.html"} <= pages
    assert 'id="make_predict"' in (tmp_path / "gst_jax" / "predict.html").read_text()
    assert 'id="Predictor"' in (tmp_path / "gst_jax" / "crowdnav.html").read_text()


def test_the_quick_start_runs_as_the_readme_writes_it(tmp_path):
    readme = (ROOT / "README.md").read_text()
    block = re.search(r"## Quick start.*?```bash\n(.*?)```", readme, re.S).group(1)
    commands = [line.split() for line in block.splitlines() if line.startswith("python3 -m gst_jax")]
    assert len(commands) == 2
    outputs = []
    for command in commands:
        command = [sys.executable if word == "python3" else word for word in command]
        command = [str(tmp_path / word) if word.endswith(".png") else word for word in command]
        outputs.append(subprocess.run(command, cwd=ROOT, capture_output=True, text=True,
                                      check=True).stdout)
    shown = re.search(r"```\n(model .*?)```", readme, re.S).group(1).splitlines()
    assert [line.split() for line in shown] == [line.split() for line in outputs[0].splitlines()
                                                if line.startswith(("model", "GST ", "constant"))]
    assert (tmp_path / "zara1.png").stat().st_size > 10_000
