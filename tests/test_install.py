"""The package installs whole outside the checkout: a built wheel holds every package of the
source tree, and in a fresh environment, run from another folder, it finds its bundled scenes
and shipped models and runs what a robot runs (a stream with conformal regions, the conformal
command, the navigation task).

Nothing here depends on what the test's environment happens to carry: the wheel is built with
build isolation, so pip fetches the build backend pyproject.toml names (setuptools>=68, whose
bdist_wheel needs no `wheel` package) from the package index, as `pip install .` does for a
user; a fresh venv with pip 23.2 and setuptools 65.5 and no `wheel` builds it the same way.
One wheel and one environment serve every test of the file (a module fixture)."""

from __future__ import annotations

import json
import shutil
import site
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path
from typing import Callable, NamedTuple

import pytest

ROOT = Path(__file__).parents[1]


class Installed(NamedTuple):
    wheel: Path
    env_dir: Path
    elsewhere: Path                     # a folder outside the checkout, where commands run
    run: Callable[..., str]             # run(*args) -> stdout of the wheel's python


def _site_folders() -> list[str]:
    """Where this interpreter's installed packages live (jax, flax, ...), not the checkout."""
    folders = [*site.getsitepackages(), sysconfig.get_paths()["purelib"],
               sysconfig.get_paths()["platlib"]]
    return list(dict.fromkeys(f for f in folders if Path(f).is_dir()))


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Installed:
    tmp_path = tmp_path_factory.mktemp("install")
    # The wheel is built from a copy of what it is made of: setuptools copies into the source
    # tree's build/ and takes whatever an earlier build left there, so a package the build
    # no longer finds would still be shipped from a checkout that once had it built.
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    for folder in ("gst_jax", "data"):
        shutil.copytree(ROOT / folder, source / folder,
                        ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "-q",
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
        result = subprocess.run([str(python), *args], cwd=elsewhere, capture_output=True,
                                text=True)
        assert result.returncode == 0, result.stderr[-3000:]
        return result.stdout

    return Installed(wheel, env_dir, elsewhere, run)


def test_the_wheel_holds_every_package_of_the_source_tree(installed):
    names = zipfile.ZipFile(installed.wheel).namelist()
    packages = {path.parent.relative_to(ROOT).as_posix()
                for path in (ROOT / "gst_jax").rglob("__init__.py")}
    assert {"gst_jax", "gst_jax/conformal", "gst_jax/simulate"} <= packages
    assert sorted(p for p in packages if f"{p}/__init__.py" not in names) == []
    # The bundled data/, as gst_jax.datasets: every file of it.
    data = {path.relative_to(ROOT / "data").as_posix()
            for path in (ROOT / "data").rglob("*") if path.is_file()}
    shipped = {name.removeprefix("gst_jax/datasets/") for name in names
               if name.startswith("gst_jax/datasets/")}
    assert data and data <= shipped


def test_a_built_wheel_runs_data_stats_and_predict_from_any_folder(installed):
    run = installed.run
    where = run("-c", "import gst_jax, gst_jax.data as d; print(gst_jax.__file__); "
                      "print(d.default_data_dir())").split()
    assert all(str(installed.env_dir) in path for path in where), where
    stats = json.loads(run("-m", "gst_jax.data", "stats", "--scene", "hotel", "--json"))
    assert stats["scenes"]["hotel"]["test"]["windows"] > 0
    # A shipped model predicts the bundled sample of own data (small: one compile, seconds).
    sample = Path(where[1]) / "samples" / "crowd_10hz.txt"
    run("-m", "gst_jax.predict", "pretrained:hotel_d", "--data", str(sample), "--fps", "10",
        "--units", "cm", "--samples", "1", "--out", "sample.ndjson")
    rows = (installed.elsewhere / "sample.ndjson").read_text().splitlines()
    assert sum('"prediction_number"' in row for row in rows) > 100


STREAM = """
import numpy as np, gst_jax.stream
from gst_jax.runs import load_model
from gst_jax.conformal import Regions
from gst_jax.stream import Stream

run = load_model("pretrained:crowdnav_sj")
stream = Stream(run, regions=Regions("dtaci", alpha=0.1))
for step in range(8):
    out = stream.step(np.array([1, 2]), np.array([[0.5 * step, 0.0], [4.0, 0.3 * step]]))
print(gst_jax.stream.__file__)
print(out.ids.tolist(), out.futures.shape, out.radii.shape, bool(np.isfinite(out.radii).all()))
"""


def test_the_robot_path_runs_from_the_installed_wheel(installed):
    """A stream with DtACI regions, the conformal command and the navigation task, each on a
    small input (CrowdNav++'s small predictor: a few compiles, the longest the navigation
    loop's)."""
    run = installed.run
    where, streamed = run("-c", STREAM).splitlines()
    assert str(installed.env_dir) in where
    assert streamed == "[1, 2] (2, 5, 2) (2, 5) True"
    sample = installed.env_dir.glob("lib/python*/site-packages/gst_jax/datasets/samples/"
                                    "crowdnav_orca/orca-humans20-seed101-episode0.txt")
    measured = json.loads(run("-m", "gst_jax.conformal", "pretrained:crowdnav_sim", "--data",
                              str(next(sample)), "--fps", "4", "--split", "all",
                              "--max-frames", "30", "--json"))
    assert measured["frames"] == 30 and len(measured["coverage"]) == 5
    navigated = json.loads(run("-m", "gst_jax.navigate", "evaluate", "--episodes", "2",
                               "--plans", "66", "--workdir", "navigate", "--json"))
    assert navigated["episodes"] == 2
    assert navigated["success"] + navigated["collision"] + navigated["timeout"] == 1.0
