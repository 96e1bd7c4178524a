"""Every shipped pretrained model loads and reproduces its recorded fixed-key AOE; its weights
(model.safetensors, config.json) agree with its record (meta.json) and ship in the wheel."""

from __future__ import annotations

import fnmatch
import json
import re
import warnings
from pathlib import Path

import pytest

from gst_jax import load_pretrained, pretrained
from gst_jax.config import CROWD_SCENES, DataConfig, ModelConfig, TrainConfig
from gst_jax.errors import RunError
from gst_jax.io.workdir import WorkDir
from gst_jax.model import weights
from gst_jax.pretrained import export
from gst_jax.pretrained.__main__ import main as pretrained_main
from gst_jax.pretrained.export import check_aoe, check_data_config
from gst_jax.training.loop import fit


def test_at_least_one_model_is_shipped():
    assert pretrained.available()


@pytest.mark.parametrize("name", pretrained.available())
def test_pretrained_model_reproduces_its_recorded_aoe(name):
    meta = pretrained.load_meta(name)
    config, params = load_pretrained(name)
    aoe = check_aoe(config, params, check_data_config(meta))
    assert abs(aoe - meta["check"]["aoe"]) < 1e-3


@pytest.mark.parametrize("name", pretrained.available())
def test_a_shipped_model_is_a_weights_folder_that_agrees_with_its_record(name, tmp_path):
    """Its config.json holds its record's fields and is covered by its own checksum: as
    shipped it passes the check (a copy of it alone gets as far as the missing weights, with
    no warning of a missing checksum), and with one field edited it is refused."""
    folder, meta = pretrained.folder(name), pretrained.load_meta(name)
    config = weights.read_config(folder)
    for key in ("model", "data", "train", "epoch", "source", "licence", "commands"):
        assert config[key] == meta[key], key
    assert re.fullmatch("[0-9a-f]{64}", config["config_sha256"])
    shipped, edited = tmp_path / "shipped", tmp_path / "edited"
    edit = {**config, "source": config["source"] + "."}
    for copy, fields in ((shipped, config), (edited, edit)):
        copy.mkdir()
        (copy / "config.json").write_text(json.dumps(fields, indent=2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(RunError, match="model.safetensors: no such file"):
            weights.load(shipped)
    with pytest.raises(RunError, match="its fields' SHA-256 .* the file was edited"):
        weights.load(edited)
    assert meta["commands"] and meta["source"]
    if name.startswith("crowdnav_sj"):             # made by others: their licence beside it
        assert meta["licence"].startswith("MIT") and sorted(folder.glob("LICENSE.*"))


def test_the_list_says_why_a_model_has_no_test_figures_instead_of_nan(capsys):
    """CrowdNav++'s models were listed as `AOE nan FOE nan` (issue 74)."""
    pretrained_main(["list"])
    listed = capsys.readouterr().out
    assert "nan" not in listed.lower()
    for name in pretrained.available():
        meta = pretrained.load_meta(name)
        line = next(line for line in listed.splitlines() if line.startswith(f"{name}: "))
        if meta["test_metrics"]:
            assert f"AOE {meta['test_metrics']['aoe']:.3f} FOE " in line
        else:
            checked_on = meta["check"].get("data", meta["data"])["scene"]
            assert f"AOE - FOE - (no test evaluation recorded: trained on {meta['data']['scene']}" \
                   f"; its fixed-key check: AOE {meta['check']['aoe']:.3f} on 4 test windows " \
                   f"of {checked_on}, 2 samples)" in line
    assert "crowdnav_sj: epoch 100, AOE - FOE - " in listed


def test_every_model_states_its_time_step_and_the_speed_range_measured_for_it(capsys):
    """SPEED_RANGES holds what experiments/speed_range.py published for every shipped model,
    at the model's own grid; `list` and the card (SOURCES.md) say it."""
    published = json.loads((Path(pretrained.__file__).parents[2] / "results"
                             / "speed_range.json").read_text())["models"]
    assert sorted(pretrained.SPEED_RANGES) == pretrained.available()
    pretrained_main(["list"])
    listed = capsys.readouterr().out
    card = (pretrained.ROOT / "SOURCES.md").read_text()
    for name, speeds in pretrained.SPEED_RANGES.items():
        measured, grid = published[name], ModelConfig.from_dict(
            pretrained.load_meta(name)["model"]).grid
        assert (measured["step_s"], measured["obs_len"], measured["pred_len"]) == (
            grid.step_s, grid.obs_len, grid.pred_len)
        low, high = measured["range"]["low"], measured["range"]["high"]
        assert speeds == (None if low is None else (low, high)), name
        text = "none" if low is None else f"{low:g}" if low == high else f"{low:g}-{high:g}"
        assert (f"| `{name}` | {grid.step_s:g} s | {grid.obs_len} + {grid.pred_len} | {text} |"
                in card), name
        assert (f"time step {grid.step_s:g} s, {grid.obs_len} observed + {grid.pred_len} "
                f"predicted steps; walking speeds predicted sensibly: "
                f"{'none from 0.25 to 6' if low is None else text} m/s" in listed), name


def test_the_wheel_carries_every_file_of_the_shipped_models():
    tomllib = pytest.importorskip("tomllib")      # Python 3.11+
    root = Path(pretrained.__file__).parents[1]
    pyproject = tomllib.loads((root.parent / "pyproject.toml").read_text())
    globs = pyproject["tool"]["setuptools"]["package-data"]["gst_jax"]
    shipped = [path.relative_to(root).as_posix() for name in pretrained.available()
               for path in pretrained.folder(name).rglob("*") if path.is_file()]
    assert shipped and "pretrained/SOURCES.md" in globs
    assert not [path for path in shipped if not any(fnmatch.fnmatch(path, glob)
                                                    for glob in globs)]


def test_the_general_model_is_trained_on_crowd_and_shipped_with_its_score_on_every_scene(
        tmp_path, monkeypatch):
    run = tmp_path / "crowd-run"
    # One encoder layer: exporting does not depend on the depth, and it compiles faster.
    fit(ModelConfig(encoder_layers=1), DataConfig(scene="crowd"), TrainConfig(
        epochs=1, batch_size=4, max_train_windows=4, checkpoint_every=1), run)
    monkeypatch.setattr(export, "ROOT", tmp_path / "shipped")
    with pytest.raises(RunError, match="no test evaluation on eth at epoch 1"):
        export.export(run, "crowd_d")

    for k, scene in enumerate(CROWD_SCENES):    # as `experiments/crowd.py --train` records them
        WorkDir(run).write_evaluation(DataConfig(scene=scene), "test", 1, {"aoe": k}, "")
    folder = export.export(run, "crowd_d")
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["data"]["scene"] == "crowd"
    assert weights.load(folder).config["source"] == meta["source"] == str(run.absolute())
    assert {scene: m["aoe"] for scene, m in meta["test_metrics_per_scene"].items()} == {
        scene: k for k, scene in enumerate(CROWD_SCENES)}
