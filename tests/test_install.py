"""The package installs outside the checkout: a built wheel, in a fresh environment, run from
another folder, finds its bundled scenes and shipped models.

Nothing here depends on what the test's environment happens to carry: the wheel is built with
build isolation, so pip fetches the build backend pyproject.toml names (setuptools>=68, whose
bdist_wheel needs no `wheel` package) from the package index, as `pip install .` does for a
user; a fresh venv with pip 23.2 and setuptools 65.5 and no `wheel` builds it the same way."""

from __future__ import annotations

import json
import site
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

ROOT = Path(__file__).parents[1]


def _site_folders() -> list[str]:
    """Where this interpreter's installed packages live (jax, flax, ...), not the checkout."""
    folders = [*site.getsitepackages(), sysconfig.get_paths()["purelib"],
               sysconfig.get_paths()["platlib"]]
    return list(dict.fromkeys(f for f in folders if Path(f).is_dir()))


def test_a_built_wheel_runs_data_stats_and_predict_from_any_folder(tmp_path):
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-q",
                    "-w", str(wheels)], check=True, cwd=tmp_path)
    [wheel] = wheels.glob("gst_jax-*.whl")
    # A fresh environment that sees the dependencies this interpreter has installed (jax,
    # flax, ...: its site folders, listed in a .pth file) but not the checkout, whose editable
    # hook only runs from a site folder's own .pth: gst_jax comes from the wheel alone.
    # --ignore-installed: the editable gst_jax's metadata is visible there too; pip must
    # install the wheel beside it, not call it satisfied (nor touch it).
    env_dir = tmp_path / "env"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    python = env_dir / "bin" / "python"
    [env_site] = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True, text=True, check=True).stdout.split()
    (Path(env_site) / "test_install_dependencies.pth").write_text(
        "\n".join(_site_folders()) + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q",
                    "--no-deps", "--ignore-installed", str(wheel)], check=True)
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
