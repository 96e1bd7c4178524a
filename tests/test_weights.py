"""Weights anyone can load (gst_jax.model.weights): every model exports to model.safetensors
plus config.json, with the file's SHA-256, and loads back checked, without pickle or torch.

The CrowdNav++ models shipped as `pretrained:crowdnav_sj` and `pretrained:crowdnav_sj_rand`
are CrowdNav++'s public checkpoints converted (github.com/Shuijing725/CrowdNav_Prediction_AttnGraph,
MIT: (c) 2023 Shuijing Liu, gst_updated/ (c) 2021 Zhe Huang); they answer as CrowdNav++'s own
predictor does on tests/fixtures/crowdnav_parity.npz (tests/test_crowdnav.py).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
import sys
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest
import safetensors.numpy

import gst_jax
from gst_jax import crowdnav, evaluate, pretrained
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.errors import RunError
from gst_jax.model import weights
from gst_jax.pretrained.__main__ import main as pretrained_main
from gst_jax.runs import load_model, load_run
from gst_jax.training.loop import fit
from gst_jax.training.state import abstract_train_state

FIXTURE = np.load(Path(__file__).parent / "fixtures" / "crowdnav_parity.npz")
SHIPPED_CROWDNAV = {"crowdnav_sj": "seed1000", "crowdnav_sj_rand": "seed1000_rand"}
TINY_MODEL = ModelConfig(node_dim=16, edge_dim=32, encoder_layers=1, lstm_hidden=16)
TINY_RUN = TrainConfig(epochs=1, batch_size=8, max_train_windows=8, checkpoint_every=1)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, Path]:
    """A tiny trained run and its export by the command (`export RUN --format safetensors
    --out DIR`)."""
    folder = tmp_path_factory.mktemp("weights")
    fit(TINY_MODEL, DataConfig(scene="zara1"), TINY_RUN, folder / "run")
    pretrained_main(["export", str(folder / "run"), "--format", "safetensors",
                     "--out", str(folder / "exported")])
    return folder / "run", folder / "exported"


def _leaves(params) -> list[np.ndarray]:
    return [np.asarray(leaf) for leaf in jax.tree.leaves(params)]


def _copy(exported: Path, to: Path) -> Path:
    shutil.copytree(exported, to)
    return to


def _one_line(error: pytest.ExceptionInfo) -> str:
    message = str(error.value)
    assert "\n" not in message
    return message


def _config_sha256(config: dict) -> str:
    """config.json's own checksum as documented: SHA-256 of its other fields as canonical
    JSON (sorted keys, no spaces, ASCII). NaN is written as JSON's `NaN`, as a hostile hand
    would: the loader must refuse it by its range, not by failing to encode it."""
    fields = {k: v for k, v in config.items() if k != "config_sha256"}
    return hashlib.sha256(json.dumps(fields, sort_keys=True, separators=(",", ":"))
                          .encode()).hexdigest()


def _hostile(exported: Path, to: Path, tensors: dict | None = None,
             model: dict | None = None, **fields) -> Path:
    """A copy of the export with its tensors, model fields or other fields changed, and both
    checksums recomputed to match: only the loader's own checks stand between it and a
    model."""
    folder = _copy(exported, to)
    config = json.loads((folder / "config.json").read_text())
    if tensors is not None:
        safetensors.numpy.save_file(tensors, str(folder / "model.safetensors"))
        config["sha256"] = hashlib.sha256((folder / "model.safetensors").read_bytes()).hexdigest()
    for section, changes in (("model", model or {}), *(
            (name, value) for name, value in fields.items() if isinstance(value, dict))):
        config[section] = {**config[section], **changes}
    config.update({k: v for k, v in fields.items() if not isinstance(v, dict)})
    config["config_sha256"] = _config_sha256(config)
    (folder / "config.json").write_text(json.dumps(config, indent=2))
    return folder


def test_a_trained_run_exports_and_loads_back_to_the_same_parameters_and_predictions(trained):
    run_dir, exported = trained
    original = load_run(run_dir)
    config = json.loads((exported / "config.json").read_text())
    assert config["format"] == weights.FORMAT and config["epoch"] == original.epoch == 1
    assert config["model"] == dataclasses.asdict(TINY_MODEL)
    assert config["data"]["scene"] == "zara1" and config["train"]["epochs"] == 1
    assert config["source"] == str(run_dir.absolute()) and config["licence"] is None
    assert config["commands"][0].startswith("python -m gst_jax.pretrained export ")
    # The file: plain safetensors, '/'-joined Flax paths, the layout of a training's params.
    tensors = safetensors.numpy.load_file(str(exported / "model.safetensors"))
    assert tensors["lstm/weight_ih"].shape == (16, 4 * 16)
    assert tensors["node_encoder_layers_0/in_proj/kernel"].shape == (16, 3 * 16)
    assert tensors["edge_selector/mlp_out_bias"].shape == ()
    layout = weights.flatten_abstract(abstract_train_state(TINY_MODEL).params)
    assert {k: v.shape for k, v in tensors.items()} == {k: v.shape for k, v in layout.items()}

    for name in (exported, exported / "model.safetensors"):
        loaded = load_model(name)
        assert loaded.model_config == original.model_config and loaded.epoch == 1
        assert loaded.data_config == original.data_config
        assert loaded.train_config == original.train_config and loaded.workdir is None
        assert jax.tree.structure(loaded.params) == jax.tree.structure(original.params)
        for mine, theirs in zip(_leaves(loaded.params), _leaves(original.params)):
            assert mine.dtype == theirs.dtype and np.array_equal(mine, theirs)

    t = np.arange(8.0)[:, None]
    observed = np.full((1, 8, 3, 2), np.nan)
    observed[0, :, 0] = np.hstack([0.5 * t, 0 * t])
    observed[0, :, 1] = np.hstack([6 - 0.45 * t, 0.3 + 0 * t])
    observed[0, 5:, 2] = np.hstack([3 + 0 * t[5:], -3 + 0.4 * t[5:]])
    predict = gst_jax.make_predict(TINY_MODEL, num_samples=3)
    batch = gst_jax.make_batch(observed, grid=TINY_MODEL.grid)
    expected = predict(original.params, jax.random.key(7), batch)
    got = predict(load_model(exported).params, jax.random.key(7), batch)
    np.testing.assert_array_equal(np.asarray(got.positions), np.asarray(expected.positions))
    np.testing.assert_array_equal(np.asarray(got.sampled_adjacency),
                                  np.asarray(expected.sampled_adjacency))
    with pytest.raises(RunError, match="holds the parameters of epoch 1 only, not of epoch 2"):
        load_model(exported, epoch=2)


def test_a_flipped_byte_or_a_missing_file_is_refused_in_one_line_naming_it(trained, tmp_path):
    _, exported = trained
    flipped = _copy(exported, tmp_path / "flipped")
    raw = bytearray((flipped / "model.safetensors").read_bytes())
    raw[len(raw) // 2] ^= 0x01
    (flipped / "model.safetensors").write_bytes(bytes(raw))
    with pytest.raises(RunError) as error:
        load_model(flipped)
    assert _one_line(error).startswith(f"{flipped / 'model.safetensors'}: SHA-256 ")
    assert "is not the" in str(error.value) and "damaged" in str(error.value)

    truncated = _copy(exported, tmp_path / "truncated")
    (truncated / "model.safetensors").write_bytes(bytes(raw[:100]))
    with pytest.raises(RunError, match="SHA-256"):
        load_model(truncated / "model.safetensors")

    missing = _copy(exported, tmp_path / "missing")
    (missing / "model.safetensors").unlink()
    with pytest.raises(RunError) as error:
        load_model(missing)
    assert _one_line(error) == f"{missing / 'model.safetensors'}: no such file"

    no_config = _copy(exported, tmp_path / "no_config")
    (no_config / "config.json").unlink()
    with pytest.raises(RunError) as error:
        load_model(no_config)
    assert _one_line(error).startswith(f"{no_config / 'config.json'}: no such file")
    with pytest.raises(RunError, match=r"nowhere/config.json: no such file"):
        load_model(tmp_path / "nowhere" / "model.safetensors")


def test_weights_of_another_layout_than_their_config_are_refused_in_one_line(trained,
                                                                              tmp_path):
    _, exported = trained
    tensors = safetensors.numpy.load_file(str(exported / "model.safetensors"))

    def rewritten(name: str, changed: dict, dropped: tuple = ()) -> Path:
        """The export with its tensors changed and its checksums matching them: only the
        layout check stands between the file and the model."""
        kept = {k: v for k, v in {**tensors, **changed}.items() if k not in dropped}
        return _hostile(exported, tmp_path / name, kept)

    wrong = rewritten("shape", {"lstm/weight_ih": tensors["lstm/weight_ih"].T.copy()})
    with pytest.raises(RunError) as error:
        load_model(wrong)
    assert _one_line(error) == (
        f"{wrong / 'model.safetensors'}: not the parameters of its model config: "
        "lstm/weight_ih is float32[64, 16], expected float32[16, 64]")
    other = rewritten("other", {"lstm/weight_ih": tensors["lstm/weight_ih"].astype(np.float64),
                                "extra/kernel": np.zeros(2, np.float32)}, ("hidden2pos/bias",))
    with pytest.raises(RunError) as error:
        load_model(other)
    assert _one_line(error).endswith(
        "no hidden2pos/bias; unexpected extra/kernel; lstm/weight_ih is float64[16, 64], "
        "expected float32[16, 64]")
    # A command says it in one line.
    with pytest.raises(SystemExit) as error:
        evaluate.main([str(wrong), "--scene", "zara1", "--max-windows", "1"])
    assert str(error.value).startswith("error: ") and "lstm/weight_ih is" in str(error.value)
    assert "\n" not in str(error.value)


def test_non_finite_weights_are_refused_in_one_line_naming_file_and_tensor(trained, tmp_path):
    """NaN or inf parameters with a recomputed checksum loaded and predicted NaN for every
    person (issue 74)."""
    _, exported = trained
    tensors = safetensors.numpy.load_file(str(exported / "model.safetensors"))
    weight = tensors["lstm/weight_ih"].copy()
    weight[3, 5], weight[7, 1] = np.nan, -np.inf
    nan = _hostile(exported, tmp_path / "nan", {**tensors, "lstm/weight_ih": weight})
    with pytest.raises(RunError) as error:
        load_model(nan)
    assert _one_line(error) == (
        f"{nan / 'model.safetensors'}: tensor lstm/weight_ih holds 2 non-finite value(s) of "
        "1024 (the first, nan, at index [3, 5]): parameters must be finite")
    inf = _hostile(exported, tmp_path / "inf", {
        **tensors, "edge_selector/mlp_out_bias": np.array(np.inf, np.float32)})
    with pytest.raises(RunError, match=r"inf/model.safetensors: tensor edge_selector/"
                                       r"mlp_out_bias holds 1 non-finite value\(s\) of 1 "
                                       r"\(the first, inf, at index \[\]\)"):
        weights.load(inf)
    # Nor is such a model written.
    broken = jax.tree.map(lambda leaf: leaf * np.nan, load_model(exported).params)
    with pytest.raises(RunError, match=r"model.safetensors \(not written\): tensor "):
        weights.save(tmp_path / "not_written", TINY_MODEL, broken)
    assert not (tmp_path / "not_written").exists()


@pytest.mark.parametrize("section, field, value, problem", [
    ("model", "pred_len", 10**6, "must be an integer from 1 to 1000"),
    ("model", "pred_len", 0, "must be an integer from 1 to 1000"),
    ("model", "obs_len", -3, "must be an integer from 1 to 1000"),
    ("model", "step_s", float("nan"), "must be a finite number in [0.001, 60]"),
    ("model", "dropout", 1.0, "must be a finite number in [0, 1)"),
    ("model", "pred_len", 12.0, "must be an integer from 1 to 1000"),
    ("model", "attention", "sideways", "must be one of release, masked"),
    ("data", "scale", float("inf"), "must be a finite number in (0, 1e+06]"),
    ("train", "epochs", 0, "must be an integer from 1 to 1000000"),
    (None, "epoch", -1, "must be an integer from 0 to 1000000"),
])
def test_config_fields_out_of_range_are_refused_naming_file_field_and_value(
        trained, tmp_path, section, field, value, problem):
    """Values that keep the parameters' layout loaded, checksums recomputed (issue 74)."""
    _, exported = trained
    changes = {section: {field: value}} if section else {field: value}
    folder = _hostile(exported, tmp_path / "hostile", **changes)
    with pytest.raises(RunError) as error:
        weights.load(folder)
    name = f"{section}.{field}" if section else field
    shown = "nan" if value != value else "inf" if value == float("inf") else repr(value)
    assert _one_line(error) == f"{folder / 'config.json'}: {name} is {shown}: {problem}"


def test_save_writes_nothing_that_load_would_refuse(trained, tmp_path):
    _, exported = trained
    params = load_model(exported).params
    with pytest.raises(RunError) as error:
        weights.save(tmp_path / "grid", dataclasses.replace(TINY_MODEL, pred_len=0), params)
    assert _one_line(error) == (f"{tmp_path / 'grid' / 'config.json'} (not written): "
                                "model.pred_len is 0: must be an integer from 1 to 1000")
    with pytest.raises(RunError, match=r"config.json \(not written\): its record holds a value "
                                       "that JSON cannot"):
        weights.save(tmp_path / "record", TINY_MODEL, params, {"crowdnav_args": {"lr": {1}}})
    assert not (tmp_path / "grid").exists() and not (tmp_path / "record").exists()


def test_the_config_checksum_is_the_sha256_of_its_other_fields_as_canonical_json():
    """`config_sha256` as docs describe it, against a value known independently of the code:
    the canonical JSON of these fields is written out below (sorted keys, nested ones too, no
    spaces, non-ASCII escaped, `config_sha256` itself left out), and its SHA-256 was computed
    once by `printf '%s' '<it>' | sha256sum`. The test's own `_config_sha256`, which forges
    the checksums of hostile folders, is held to it too."""
    canonical = ('{"epoch":3,"format":"gst_jax-weights","licence":"MIT \\u00a9 2022",'
                 '"model":{"pred_len":12,"step_s":0.4},"sha256":"00ff"}')
    known = "9391d2bcebe262b769e9a8d029a48eb10b16f016eef6f949ff7d568070f49ac2"
    assert hashlib.sha256(canonical.encode("ascii")).hexdigest() == known
    config = {"sha256": "00ff", "model": {"step_s": 0.4, "pred_len": 12},
              "licence": "MIT \u00a9 2022", "format": "gst_jax-weights", "epoch": 3,
              "config_sha256": "whatever was recorded"}
    assert json.loads(canonical) == {k: v for k, v in config.items() if k != "config_sha256"}
    assert weights.config_digest(config) == _config_sha256(config) == known
    # A different recorded checksum or key order is the same content; one field is not.
    assert weights.config_digest(dict(reversed({**config, "config_sha256": "x"}.items()))) == known
    assert weights.config_digest({**config, "model": {"step_s": 0.4, "pred_len": 8}}) != known
    assert weights.config_digest({**config, "epoch": 3.0}) != known        # 3.0 is not 3
    with pytest.raises(ValueError):
        weights.config_digest({**config, "epoch": float("nan")})


def test_an_edit_of_config_json_is_detected_by_its_checksum(trained, tmp_path):
    _, exported = trained
    config = json.loads((exported / "config.json").read_text())
    assert config["config_sha256"] == _config_sha256(config)
    # Reformatted (indent, key order) it is the same content, and loads.
    same = _copy(exported, tmp_path / "reformatted")
    (same / "config.json").write_text(json.dumps(dict(reversed(config.items())), indent=7))
    assert weights.load(same).config == config
    # An edit within the ranges that keeps the layout: refused.
    for field, value in (("pred_len", 8), ("step_s", 0.5)):
        edited = _copy(exported, tmp_path / field)
        (edited / "config.json").write_text(json.dumps(
            {**config, "model": {**config["model"], field: value}}, indent=2))
        with pytest.raises(RunError) as error:
            weights.load(edited)
        assert _one_line(error).startswith(f"{edited / 'config.json'}: its fields' SHA-256 ")
        assert error.value.args[0].endswith("config_sha256 records: the file was edited or "
                                            "damaged after export")
    # A NaN where no range is checked cannot be covered: refused too.
    odd = _copy(exported, tmp_path / "odd")
    (odd / "config.json").write_text(json.dumps({**config, "crowdnav_args": {"lr": np.nan}}))
    with pytest.raises(RunError, match="holds a NaN or infinite value, which its "
                                       "config_sha256 cannot cover"):
        weights.load(odd)


def test_a_folder_exported_before_config_json_had_a_checksum_loads_with_a_warning(
        trained, tmp_path):
    """Models handed out before keep loading (range-checked), and say how to re-export."""
    _, exported = trained
    old = _copy(exported, tmp_path / "old")
    config = json.loads((old / "config.json").read_text())
    del config["config_sha256"]
    (old / "config.json").write_text(json.dumps(config, indent=2))
    with pytest.warns(UserWarning, match=r"old/config.json has no config_sha256 \(exported "
                                         r"before .* export .*old --out NEW_FOLDER"):
        loaded = load_model(old)
    for mine, theirs in zip(_leaves(loaded.params), _leaves(load_model(exported).params)):
        assert np.array_equal(mine, theirs)
    with pytest.warns(UserWarning, match="has no config_sha256"):
        pretrained_main(["export", str(old), "--out", str(tmp_path / "new")])
    assert json.loads((tmp_path / "new" / "config.json").read_text())["config_sha256"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        weights.load(tmp_path / "new")
    # Its fields are checked all the same.
    config["model"]["pred_len"] = 0
    (old / "config.json").write_text(json.dumps(config, indent=2))
    with pytest.raises(RunError, match="model.pred_len is 0: must be an integer from 1 to"):
        weights.load(old)


def test_an_exported_folder_is_a_model_name_for_the_commands(trained, capsys):
    _, exported = trained
    evaluate.main([str(exported), "--scene", "zara1", "--max-windows", "1", "--samples", "1",
                   "--no-kde", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert result["model"] == str(exported) and result["epoch"] == 1
    assert result["windows"] == 1 and np.isfinite(result["aoe"])


@pytest.mark.parametrize("name", SHIPPED_CROWDNAV)
def test_the_shipped_crowdnav_models_load_without_torch_and_answer_as_crowdnav_does(
        name, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)           # `import torch` would fail
    predictor = crowdnav.load(f"pretrained:{name}")
    checkpoint = SHIPPED_CROWDNAV[name]
    output_traj, output_mask = predictor(FIXTURE["input_traj"], FIXTURE["input_mask"])
    np.testing.assert_allclose(np.asarray(output_traj), FIXTURE[f"{checkpoint}/output_traj"],
                               atol=1e-5, rtol=0)
    np.testing.assert_array_equal(np.asarray(output_mask), FIXTURE[f"{checkpoint}/output_mask"])
    # The parameters are those of CrowdNav++'s checkpoint, bit for bit, and so is the config.
    prefix = f"{checkpoint}/state_dict/"
    args = json.loads(str(FIXTURE[f"{checkpoint}/args"]))
    converted = crowdnav.from_state_dict(
        {key[len(prefix):]: FIXTURE[key] for key in FIXTURE.files if key.startswith(prefix)},
        args)
    assert predictor.config == converted.config == crowdnav.model_config(args)
    for mine, theirs in zip(_leaves(predictor.params), _leaves(converted.params)):
        assert np.array_equal(mine, theirs)

    # The same model is a gst_jax model too: a Run, and a predictor from it.
    run = load_model(f"pretrained:{name}")
    assert run.model_config == predictor.config and run.epoch == args["num_epochs"] == 100
    assert run.train_config.seed == args["random_seed"] and not run.train_config.rotate
    assert "not bundled" in run.data_config.scene
    again = crowdnav.from_run(run)(FIXTURE["input_traj"], FIXTURE["input_mask"])[0]
    np.testing.assert_array_equal(np.asarray(again), np.asarray(output_traj))
    meta = pretrained.load_meta(name)
    assert meta["crowdnav_args"] == args and meta["licence"].startswith("MIT")
    assert "Shuijing725/CrowdNav_Prediction_AttnGraph" in meta["source"]
    for licence, holder in (("LICENSE.CrowdNav_Prediction_AttnGraph", "2023 Shuijing Liu"),
                            ("LICENSE.gst_updated", "2021 Zhe Huang")):
        text = (pretrained.folder(name) / licence).read_text()
        assert text.startswith("MIT License") and f"Copyright (c) {holder}" in text


def test_only_crowdnav_kinds_of_model_become_crowdnav_predictors():
    with pytest.raises(ValueError, match="pretrained:eth_d: CrowdNav\\+\\+'s predictor is a "
                                         "full-connection"):
        crowdnav.from_run(load_model("pretrained:eth_d"))
    assert crowdnav.load("pretrained:crowdnav_sim").config.obs_len == 5
