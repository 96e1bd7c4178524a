"""Your own data: any rate that is a multiple of 2.5 Hz, any unit, every model, fine-tuning."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gst_jax import data
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.errors import RunError
from gst_jax.evaluation import evaluate_run
from gst_jax.io.workdir import WorkDir
from gst_jax.runs import load_model, load_run
from gst_jax.training.loop import fit
from gst_jax.training.state import hparams_for_epoch, step_key
from gst_jax.training.step import make_train_step

SAMPLE = Path(__file__).parents[1] / "data" / "samples" / "crowd_10hz.txt"
TINY = TrainConfig(epochs=1, batch_size=8, max_train_windows=8, checkpoint_every=1)


@pytest.fixture(scope="module")
def at_model_rate(tmp_path_factory) -> Path:
    """The sample pre-resampled by hand: every 4th row of 10 Hz, frame ids 0, 10, 20, ... as
    ETH/UCY number them, metres."""
    rows = np.loadtxt(SAMPLE)
    rows = rows[rows[:, 0] % 4 == 0]
    path = tmp_path_factory.mktemp("own") / "crowd_2_5hz.txt"
    path.write_text("".join(f"{int(f) * 10 // 4} {int(p)} {float(x) / 100!r} {float(y) / 100!r}\n"
                            for f, p, x, y in rows))
    return path


def _configs(at_model_rate: Path) -> tuple[DataConfig, DataConfig]:
    return (DataConfig(scene="crowd_10hz", data=str(SAMPLE), fps=10, scale=0.01),
            DataConfig(scene="crowd_2_5hz", data=str(at_model_rate)))


def test_a_10hz_file_in_centimetres_gives_the_windows_of_the_same_data_at_2_5hz(at_model_rate):
    ours, by_hand = _configs(at_model_rate)
    for split in ("train", "test", "all"):
        a, b = data.load_split(ours, split), data.load_split(by_hand, split)
        assert len(a) == len(b) > 0, split
        for x, y in zip(a.windows, b.windows):
            np.testing.assert_allclose(x.positions, y.positions, rtol=0, atol=1e-5)
            np.testing.assert_array_equal(x.position_mask, y.position_mask)


def test_train_and_evaluate_on_it_equal_the_pre_resampled_data(tmp_path, at_model_rate):
    results = []
    for config, name in zip(_configs(at_model_rate), ("a", "b")):
        summary = fit(ModelConfig(), config, TINY, tmp_path / name)
        run = load_run(tmp_path / name)
        results.append((summary["final_loss"], evaluate_run(run, config, "test", num_samples=2,
                                                            with_kde=False)))
    (loss_a, eval_a), (loss_b, eval_b) = results
    assert loss_a == pytest.approx(loss_b, rel=1e-5)
    for name in ("aoe", "foe", "min_ade", "cv_aoe"):
        assert eval_a[name] == pytest.approx(eval_b[name], rel=1e-4), name
    assert eval_a["scene"] == "crowd_10hz" and eval_a["windows"] == eval_b["windows"]


def _command(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True,
                          timeout=600, cwd=cwd)


def test_a_rate_that_is_not_a_multiple_of_2_5hz_is_refused(tmp_path):
    result = _command("gst_jax.train", "--data", str(SAMPLE), "--fps", "3",
                      "--workdir", str(tmp_path / "run"))
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines()[-1] == (
        f"error: {SAMPLE}: annotated at 3 Hz (a row every 1 frame ids at 3 per second), which "
        "is not a multiple of the model's 2.5 Hz")
    assert not (tmp_path / "run").exists()


def test_a_shipped_model_evaluates_and_plots_own_data_from_any_folder(tmp_path):
    relative = SAMPLE.relative_to(SAMPLE.parents[3])        # from the repository's parent
    result = _command("gst_jax.evaluate", "pretrained:hotel_d", "--data", str(relative),
                      "--fps", "10", "--units", "cm", "--samples", "2", "--no-kde", "--json",
                      cwd=SAMPLE.parents[3])
    assert result.returncode == 0, result.stderr
    evaluation = json.loads(result.stdout)
    assert evaluation["model"] == "pretrained:hotel_d" and evaluation["scene"] == "crowd_10hz"
    assert 0 < evaluation["aoe"] < evaluation["foe"] < 5
    figure = tmp_path / "scene.png"
    result = _command("gst_jax.plot", "scene", "pretrained:hotel_d", "--data", str(SAMPLE),
                      "--fps", "10", "--units", "cm", "--samples", "2", "--out", str(figure),
                      cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert figure.stat().st_size > 10_000


def test_fine_tuning_starts_from_the_given_parameters(tmp_path, at_model_rate):
    config = _configs(at_model_rate)[1]
    source = load_model("pretrained:hotel_d")
    train_config = dataclasses.replace(TINY, init="pretrained:hotel_d")
    summary = fit(source.model_config, config, train_config, tmp_path / "tuned")
    # One step: the epoch's loss is the loss of the shipped parameters on that step.
    step = next(iter(data.training_batches(data.load_split(config, "train").subset(range(8)),
                                           batch_size=8, seed=train_config.seed, epoch=1)))
    hparams = hparams_for_epoch(source.model_config, train_config, 1)
    loss, _ = make_train_step(source.model_config).loss_and_grads(
        source.params, step_key(train_config.seed, 1, 0), step, hparams)
    assert summary["final_loss"] == pytest.approx(float(loss), rel=1e-5)
    with pytest.raises(RunError, match="another architecture"):
        fit(ModelConfig(temporal="tcn"), config, train_config, tmp_path / "tcn")
    assert not (tmp_path / "tcn").exists()
    assert WorkDir(tmp_path / "tuned").read_metrics()[0]["epoch"] == 1
