"""The package installs outside the checkout: a built wheel, in a fresh environment, run from
another folder, finds its bundled scenes and shipped models."""

from __future__ import annotations

import json
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).parents[1]


def test_a_built_wheel_runs_data_stats_and_predict_from_any_folder(tmp_path):
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps",
                    "--no-build-isolation", "-q", "-w", str(wheels)], check=True,
                   cwd=tmp_path)
    [wheel] = wheels.glob("gst_jax-*.whl")
    # A fresh environment that sees the dependencies already installed (jax, flax, ...) but
    # not the checkout: gst_jax comes from the wheel alone.
    env_dir = tmp_path / "env"
    venv.EnvBuilder(system_site_packages=True, with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q",
                    "--no-deps", str(wheel)], check=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    def run(*args: str) -> str:
        return subprocess.run([str(python), *args], cwd=elsewhere, capture_output=True,
                              text=True, check=True).stdout

    where = run("-c", "import gst_jax, gst_jax.data as d; print(gst_jax.__file__); "
                      "print(d.default_data_dir())").split()
    assert all(str(env_dir) in path for path in where), where
    stats = json.loads(run("-m", "gst_jax.data", "stats", "--scene", "hotel", "--json"))
    assert stats["scenes"]["hotel"]["test"]["windows"] > 0
    # A shipped model predicts the bundled sample of own data (small: one compile, seconds).
    sample = Path(where[1]) / "samples" / "crowd_10hz.txt"
    run("-m", "gst_jax.predict", "pretrained:hotel_d", "--data", str(sample), "--fps", "10",
        "--units", "cm", "--samples", "1", "--out", "sample.ndjson")
    rows = (elsewhere / "sample.ndjson").read_text().splitlines()
    assert sum('"prediction_number"' in row for row in rows) > 100
