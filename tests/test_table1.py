"""experiments/table1.py, crowd.py and schedules.py: rows from work directories and shipped
models, spread over seeds; parked runs; a shorter schedule's verdict; results/ written only with
--publish, and the published tables reproduced byte for byte by their documented commands."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import _common
import crowd
import schedules
import table1
from gst_jax.io.checkpoints import Checkpointer
from gst_jax.io.workdir import WorkDir
from gst_jax.testing.drawn import bar_heights, colour_pixels, pixels_near, saved_figures

ROOT = Path(__file__).parents[1]


def _isolated(tmp_path: Path) -> list[str]:
    """The flag that keeps a test's parked runs in its own folder (not the checkout's)."""
    return ["--parked", str(tmp_path / "parked")]


def _fake_run(runs: Path, scene: str, seed: int, aoe: float, epoch_times: list[float],
              output: str = "deterministic", epochs: int = 200, schedule: str = "paper") -> None:
    workdir = table1.workdir_of(runs, scene, "paper", output, epochs, seed, schedule)
    (workdir / "eval").mkdir(parents=True)
    (workdir / "metrics.jsonl").write_text("".join(
        json.dumps({"epoch": e + 1, "epoch_time_s": t}) + "\n" for e, t in enumerate(epoch_times)))
    result = {"aoe": aoe, "aoe_std": 0.01, "foe": 2 * aoe, "foe_std": 0.02, "cv_aoe": 0.5,
              "cv_foe": 1.0, "kde_nll": -aoe, "epoch": 200, "pedestrians": 7, "protocol": "fake",
              "release_aoe_std": aoe / 2, "release_foe_std": aoe}
    (workdir / "eval" / f"{scene}-paper-test-e{epochs}.json").write_text(json.dumps(result))


def test_rows_average_seeds_fall_back_to_shipped_models_and_never_fill_in(tmp_path,
                                                                         monkeypatch):
    from gst_jax import pretrained
    monkeypatch.setattr(pretrained, "available", lambda: ["eth_d"])    # the only one shipped
    _fake_run(tmp_path / "runs", "hotel", 1000, 0.20, [30.0, 30.0])
    _fake_run(tmp_path / "runs", "hotel", 1001, 0.30, [60.0])
    table1.main([*_isolated(tmp_path), "--scenes", "hotel", "eth", "univ", "--seeds",
                 "1000,1001", "--runs", str(tmp_path / "runs"), "--workdir", str(tmp_path / "out")])
    hotel, eth, univ = json.loads((tmp_path / "out" / "table1.json").read_text())

    assert hotel["seeds"] == [1000, 1001] and hotel["spread_over"] == "seeds"
    assert hotel["aoe"] == pytest.approx(0.25) and hotel["aoe_spread"] == pytest.approx(0.05)
    assert hotel["foe"] == pytest.approx(0.50) and hotel["train_time_s"] == [60.0, 60.0]
    # eth seed 1000 is the shipped eth_d model's record; seed 1001 was never trained.
    shipped = json.loads((Path(__file__).parents[1] / "gst_jax" / "pretrained" / "eth_d"
                          / "meta.json").read_text())["test_metrics"]
    assert eth["seeds"] == [1000] and eth["aoe"] == shipped["aoe"]
    assert eth["aoe_spread"] == shipped["aoe_std"] and eth["spread_over"] == "20 runs"
    assert "aoe" not in univ                                     # nothing trained, nothing shipped
    table = (tmp_path / "out" / "table1.md").read_text()
    # Constant velocity is computed from the test split for every scene, finished or not; on
    # eth it is what evaluate_params recorded beside the shipped model.
    assert (eth["cv_aoe"], eth["cv_foe"]) == pytest.approx((shipped["cv_aoe"], shipped["cv_foe"]))
    assert "| univ | missing | missing | - | 0.50 | 1.08 | 0.52 / 1.16 |" in table
    # The release's spread statistic: the mean of the seeds' (0.10 and 0.15 for AOE).
    assert ("| hotel | 0.250 ± 0.050 | 0.500 ± 0.100 | 0.125 / 0.250 | 0.21 | 0.38 | "
            "0.34 / 0.63 |") in table
    release = ("-" if "release_aoe_std" not in shipped       # recorded before it existed
               else f"{shipped['release_aoe_std']:.3f} / {shipped['release_foe_std']:.3f}")
    assert (f"| eth | {shipped['aoe']:.3f} ± {shipped['aoe_std']:.3f} | {shipped['foe']:.3f} ± "
            f"{shipped['foe_std']:.3f} | {release} |") in table
    assert "| AVG |" not in table                                  # three scenes, no average


def test_finished_runs_are_kept_as_records_that_outlive_their_work_directories(tmp_path):
    _fake_run(tmp_path / "runs", "hotel", 1000, 0.20, [30.0, 30.0])
    argv = ["--scenes", "hotel", "--seeds", "1000", "--runs", str(tmp_path / "runs"),
            "--workdir", str(tmp_path / "out"), "--parked", str(tmp_path / "parked")]
    table1.main(argv)
    first = (tmp_path / "out" / "table1.json").read_text()
    record = json.loads((tmp_path / "out" / "runs" / "hotel-paper-d-n1-e200-seed1000.json")
                        .read_text())
    assert record["aoe"] == 0.20 and record["train_time_s"] == 60.0

    for path in sorted((tmp_path / "runs").rglob("*"), reverse=True):   # the runs are lost
        path.unlink() if path.is_file() else path.rmdir()
    table1.main(argv)
    assert (tmp_path / "out" / "table1.json").read_text() == first


def test_gaussian_table_has_kde_nll_and_averages_all_five_scenes(tmp_path):
    for k, scene in enumerate(("eth", "hotel", "univ", "zara1", "zara2")):
        _fake_run(tmp_path / "runs", scene, 1000, 0.1 * (k + 1), [60.0], output="gaussian")
    table1.main([*_isolated(tmp_path), "--output", "gaussian", "--runs", str(tmp_path / "runs"),
                 "--workdir", str(tmp_path / "out")])
    table = (tmp_path / "out" / "table1_p.md").read_text()
    assert ("| eth | 0.100 ± 0.010 | 0.200 ± 0.020 | 0.050 / 0.100 | 1.10 | 2.22 | -0.10 | "
            "0.97 / 2.12 |") in table
    assert ("| AVG | 0.300 | 0.600 | | 0.60 | 1.20 | -0.30 (paper -1.98) | 0.51 / 1.10 | | | "
            "|") in table


def test_leave_one_scene_out_table_without_runs_shows_the_baseline_and_no_average_of_ours(
        tmp_path):
    with saved_figures() as saved:
        table1.main([*_isolated(tmp_path), "--protocol", "loo", "--runs",
                     str(tmp_path / "runs"), "--workdir", str(tmp_path / "out")])
    rows = json.loads((tmp_path / "out" / "table1_loo.json").read_text())
    assert [r["scene"] for r in rows] == ["eth", "hotel", "univ", "zara1", "zara2"]
    assert all("aoe" not in r and r["cv_aoe"] > 0 and r["pedestrians"] > 0 for r in rows)
    table = (tmp_path / "out" / "table1_loo.md").read_text()
    assert "| AVG | - | - | | 0.48 | 1.02 |" in table and "No average of ours" in table
    assert "The paper did not report this protocol" in table
    # The bar figure: per scene, no bar of ours but "missing", the paper's and constant
    # velocity's of the table.
    figure = tmp_path / "out" / "table1_loo.png"
    for ax, metric in zip(saved[figure].axes, ("aoe", "foe")):
        ours, paper, cv = bar_heights(ax)
        assert np.isnan(ours).all() and [t.get_text() for t in ax.texts] == ["missing"] * 5
        np.testing.assert_allclose(paper, [r.get(f"paper_{metric}", np.nan) for r in rows])
        np.testing.assert_allclose(cv, [r[f"cv_{metric}"] for r in rows])
        assert (cv > 0).all()
    assert pixels_near(figure, "tab:orange") > 1_000        # constant velocity's bars


class _SittingEnds(BaseException):
    """The machine is given back during the second epoch."""


def test_a_parked_run_continues_from_its_copy_and_the_copy_goes_once_it_is_recorded(
        tmp_path, monkeypatch):
    from gst_jax.config import DataConfig, ModelConfig, TrainConfig
    from gst_jax.training.loop import fit

    config, zara1 = TrainConfig(epochs=2, batch_size=8, max_train_windows=8,
                                checkpoint_every=1), DataConfig(scene="zara1")
    save = Checkpointer.save

    def end_at_the_second(self, epoch, *args):
        if epoch == 2:
            raise _SittingEnds
        save(self, epoch, *args)

    with monkeypatch.context() as patched:
        patched.setattr(Checkpointer, "save", end_at_the_second)
        with pytest.raises(_SittingEnds):
            fit(ModelConfig(), zara1, config, tmp_path / "first")
    first_epoch = WorkDir(tmp_path / "first").read_metrics()
    # (a seed no shipped model has, so that the row cannot fall back to one)
    name = table1.workdir_of(Path("runs"), "zara1", "paper", "deterministic", 200, 1003).name
    parked = tmp_path / "parked" / name
    assert _common.park(tmp_path / "first", parked) == 1
    assert sorted(p.name for p in (parked / "checkpoints").iterdir()) == ["1", "checksums.json"]

    # Until it finishes, the table shows how far it got, and still no figure.
    table1.main(["--scenes", "zara1", "--seeds", "1003", "--runs", str(tmp_path / "runs"),
                  "--workdir", str(tmp_path / "results"), "--parked", str(tmp_path / "parked")])
    [row] = json.loads((tmp_path / "results" / "table1.json").read_text())
    assert row["in_progress"] == {"1003": 1} and "aoe" not in row
    assert "| zara1 | missing (seed 1003 at epoch 1 of 200) | missing |" in (
        tmp_path / "results" / "table1.md").read_text()
    assert not (tmp_path / "runs").exists()                 # reading it created nothing

    shutil.copytree(parked, tmp_path / "second")            # the next sitting, another machine
    fit(ModelConfig(), zara1, config, tmp_path / "second")
    records = WorkDir(tmp_path / "second").read_metrics()
    assert [r["epoch"] for r in records] == [1, 2] and records[:1] == first_epoch

    # Once the run's evaluation is recorded in the published records, its parked copy is
    # deleted; a table of one's own leaves the (committed) copy alone.
    _fake_run(tmp_path / "runs", "hotel", 1000, 0.20, [30.0])
    parked = tmp_path / "parked" / "hotel-paper-d-n1-e200-seed1000"
    parked.mkdir(parents=True)
    argv = ["--scenes", "hotel", "--runs", str(tmp_path / "runs"), "--parked",
            str(tmp_path / "parked")]
    table1.main([*argv, "--workdir", str(tmp_path / "mine")])
    assert parked.exists()
    monkeypatch.setattr(_common, "RESULTS", tmp_path / "published")
    table1.main([*argv, "--publish"])
    assert not parked.exists()


def test_the_general_model_is_shown_beside_each_scene_s_own_model_and_outlives_its_run(
        tmp_path, monkeypatch):
    _fake_run(tmp_path / "runs", "crowd", 1000, 0.40, [600.0])        # its union test split
    workdir = table1.workdir_of(tmp_path / "runs", "crowd", "paper", "deterministic", 200, 1000)
    for k, scene in enumerate(crowd.SCENES):
        if scene != "wildtrack":                                  # not evaluated there yet
            (workdir / "eval" / f"{scene}-paper-test-e200.json").write_text(json.dumps(
                {"aoe": 0.1 * (k + 1), "foe": 0.2 * (k + 1), "pedestrians": k + 1,
                 "cv_aoe": 0.5, "cv_foe": 1.0}))
    _fake_run(tmp_path / "runs", "hotel", 1000, 0.25, [60.0])         # hotel's own model
    argv = ["--runs", str(tmp_path / "runs"), "--workdir", str(tmp_path / "out"),
            "--parked", str(tmp_path / "parked")]
    crowd.main(argv)
    table = (tmp_path / "out" / "crowd.md").read_text()
    assert "| hotel | 2 | 0.200 / 0.400 | 0.250 / 0.500 | 0.500 / 1.000 |" in table
    assert "| lcas | 6 | 0.600 / 1.200 | - | 0.500 / 1.000 |" in table
    assert "| wildtrack | - | - | - | - |" in table
    assert "| all seven | 7 | 0.400 / 0.800 | - | 0.500 / 1.000 |" in table
    assert "Train time 10 min" in table

    evaluated = []                       # --train evaluates it where it was not evaluated yet

    def evaluate(run, data_config):
        evaluated.append((run, data_config.scene))
        (workdir / "eval" / f"{data_config.scene}-paper-test-e200.json").write_text(json.dumps(
            {"aoe": 0.9, "foe": 1.8, "pedestrians": 9, "cv_aoe": 0.5, "cv_foe": 1.0}))
    monkeypatch.setattr(crowd, "evaluate", evaluate)
    crowd.main([*_isolated(tmp_path), *argv, "--train"])
    assert evaluated == [(workdir, "wildtrack")]
    table = (tmp_path / "out" / "crowd.md").read_text()
    assert "| wildtrack | 9 | 0.900 / 1.800 | - | 0.500 / 1.000 |" in table

    for path in sorted((tmp_path / "runs").rglob("*"), reverse=True):   # the runs are lost
        path.unlink() if path.is_file() else path.rmdir()
    crowd.main(argv)
    assert (tmp_path / "out" / "crowd.md").read_text() == table

    # A record evaluated again after the fact says so in a note under the table's caption.
    record_path = tmp_path / "out" / "runs" / f"{workdir.name}.json"
    record = json.loads(record_path.read_text())
    record_path.write_text(json.dumps({**record, "note": "Evaluated again after a fix."}))
    crowd.main(argv)
    assert "min (summed epoch times), code ?.\n\nEvaluated again after a fix.\n\n| test split" in (
        tmp_path / "out" / "crowd.md").read_text()


def test_a_shorter_schedule_is_accepted_only_where_every_scene_holds_with_three_seeds(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    reference = {"aoe": 1.0, "aoe_spread": 0.05, "foe": 2.0, "foe_spread": 0.01, "seeds": [1000],
                 "train_time_s": [600.0]}
    (out / "table1.json").write_text(json.dumps(
        [{"scene": scene, **reference} for scene in ("eth", "hotel")]))
    # E = 50: eth 2 % worse (within 3 %); hotel's AOE 4 % worse (within its spread), FOE too.
    for seed in (1000, 1001, 1002):
        _fake_run(tmp_path / "runs", "eth", seed, 1.03 if seed > 1000 else 1.0, [30.0],
                  epochs=50, schedule="compressed")
        _fake_run(tmp_path / "runs", "hotel", seed, 1.04, [30.0], epochs=50, schedule="compressed")
    # E = 100: both scenes better than 200 epochs, but hotel has one seed so far.
    for seed in (1000, 1001, 1002):
        _fake_run(tmp_path / "runs", "eth", seed, 0.9, [30.0], epochs=100, schedule="compressed")
    _fake_run(tmp_path / "runs", "hotel", 1000, 0.9, [30.0], epochs=100, schedule="compressed")

    argv = ["--scenes", "eth", "hotel", "--runs", str(tmp_path / "runs"), "--workdir", str(out),
            "--reference", str(out / "table1.json")]
    with saved_figures() as saved:
        schedules.main([*argv, "--candidates", "compressed:50", "compressed:100"])
    record = json.loads((out / "schedules.json").read_text())
    assert record["verdicts"] == {"compressed:50": "rejected", "compressed:100": "open"}
    eth, hotel = record["rows"]["compressed:50"]
    assert eth["accepted"] and eth["aoe"] == pytest.approx(1.02)
    assert eth["aoe_spread"] == pytest.approx(0.03 * 2 ** 0.5 / 3)
    assert not hotel["accepted"] and hotel["foe_change_pct"] == pytest.approx(4.0)
    table = (out / "schedules.md").read_text()
    assert "| hotel | compressed:100 | 1000 | 0.900 | 1.800 | -10.0 % / -10.0 % |" in table
    # The figure: per scene and schedule, the change from 200 epochs (eth +2 % and -10 %,
    # hotel +4 % and -10 %), AOE and FOE alike here.
    for ax in saved[out / "schedules.png"].axes:
        fifty, hundred = bar_heights(ax)
        np.testing.assert_allclose(fifty, [2.0, 4.0])
        np.testing.assert_allclose(hundred, [-10.0, -10.0])
    assert colour_pixels(out / "schedules.png") > 1_000

    for seed in (1001, 1002):                          # hotel's other seeds arrive
        _fake_run(tmp_path / "runs", "hotel", seed, 0.95, [30.0], epochs=100,
                  schedule="compressed")
    schedules.main([*argv, "--candidates", "compressed:100"])
    assert json.loads((out / "schedules.json").read_text())["verdicts"] == {
        "compressed:100": "accepted"}
    with pytest.raises(SystemExit):                    # a schedule that does not exist
        schedules.main([*argv, "--candidates", "cosine:100"])


def _contents(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_by_default_the_scripts_write_a_folder_of_their_own_and_leave_results_alone(
        tmp_path, monkeypatch):
    published = _contents(ROOT / "results")
    monkeypatch.chdir(tmp_path)                     # runs/<script>/ lands here
    _fake_run(tmp_path / "runs", "hotel", 1000, 0.20, [30.0])
    _fake_run(tmp_path / "runs", "hotel", 1000, 0.90, [30.0], epochs=50, schedule="compressed")
    table1.main(["--scenes", "hotel", "eth"])
    crowd.main([])
    schedules.main(["--scenes", "hotel", "--candidates", "compressed:50"])

    assert _contents(ROOT / "results") == published
    hotel, eth = json.loads((tmp_path / "runs" / "table1" / "table1.json").read_text())
    assert hotel["aoe"] == 0.20 and hotel["seeds"] == [1000]
    # The published records (eth: seeds 1000-1002) are not this table's runs; seed 1000 falls
    # back to the shipped model, as before any record.
    assert eth["seeds"] == [1000]
    assert eth["per_seed"]["1000"]["workdir"] == "gst_jax/pretrained/eth_d"
    assert (tmp_path / "runs" / "table1" / "runs" / "hotel-paper-d-n1-e200-seed1000.json").is_file()
    assert (tmp_path / "runs" / "crowd" / "crowd.md").is_file()
    [row] = json.loads((tmp_path / "runs" / "schedules" / "schedules.json").read_text())[
        "rows"]["compressed:50"]
    assert row["aoe"] == 0.90
    published_hotel = [r for r in json.loads((ROOT / "results" / "table1.json").read_text())
                       if r["scene"] == "hotel"]
    assert [row["reference"]["aoe"]] == [r["aoe"] for r in published_hotel]  # the published 200
    with pytest.raises(SystemExit):                 # one output: a folder, or results/
        table1.main(["--publish", "--workdir", str(tmp_path / "out")])


def test_publish_writes_results_and_only_then_its_records_count(tmp_path, monkeypatch):
    monkeypatch.setattr(_common, "RESULTS", tmp_path / "results")
    _fake_run(tmp_path / "runs", "hotel", 1000, 0.20, [30.0])
    # seed 1001 finished on another machine: only its record, committed in results/runs/
    (tmp_path / "results" / "runs").mkdir(parents=True)
    (tmp_path / "results" / "runs" / "hotel-paper-d-n1-e200-seed1001.json").write_text(
        json.dumps({"aoe": 0.30, "aoe_std": 0.01, "foe": 0.6, "foe_std": 0.02, "epoch": 200,
                    "protocol": "fake", "seed": 1001, "workdir": "elsewhere",
                    "train_time_s": 60.0}))
    argv = [*_isolated(tmp_path), "--scenes", "hotel", "--seeds", "1000,1001", "--runs",
            str(tmp_path / "runs")]
    table1.main([*argv, "--workdir", str(tmp_path / "mine")])
    [mine] = json.loads((tmp_path / "mine" / "table1.json").read_text())
    assert mine["seeds"] == [1000] and not (tmp_path / "results" / "table1.md").exists()

    table1.main([*argv, "--publish"])
    [published] = json.loads((tmp_path / "results" / "table1.json").read_text())
    assert published["seeds"] == [1000, 1001] and published["aoe"] == pytest.approx(0.25)
    assert "| hotel | 0.250 ± 0.050 |" in (tmp_path / "results" / "table1.md").read_text()
    assert (tmp_path / "results" / "runs" / "hotel-paper-d-n1-e200-seed1000.json").is_file()


def test_train_trains_what_runs_lacks_though_a_record_is_published_and_a_model_shipped(
        tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(_common, "RESULTS", tmp_path / "results")
    name = "eth-paper-d-n1-e1-seed1003"
    (tmp_path / "results" / "runs").mkdir(parents=True)
    (tmp_path / "results" / "runs" / f"{name}.json").write_text(json.dumps(
        {"aoe": 9.0, "aoe_std": 0.0, "foe": 9.0, "foe_std": 0.0, "epoch": 1, "seed": 1003,
         "protocol": "paper", "workdir": "elsewhere", "train_time_s": 1.0}))
    monkeypatch.setattr(table1, "shipped_record", lambda *args: {   # as if one were shipped
        "aoe": 8.0, "aoe_std": 0.0, "foe": 8.0, "foe_std": 0.0, "epoch": 1,
        "protocol": "paper", "workdir": "gst_jax/pretrained/eth_d", "train_time_s": None})
    trained, evaluated = [], []

    def train_small(model_config, data_config, train_config, workdir):  # a smoke-sized run
        trained.append(workdir)
        _common.train(model_config, data_config, dataclasses.replace(
            train_config, batch_size=8, max_train_windows=8), workdir)

    def evaluate(workdir):          # stands in for the 20-run evaluation of the run's test split
        evaluated.append(workdir)
        (workdir / "eval" / "eth-paper-test-e1.json").parent.mkdir(exist_ok=True)
        (workdir / "eval" / "eth-paper-test-e1.json").write_text(json.dumps(
            {"aoe": 1.5, "aoe_std": 0.1, "foe": 3.0, "foe_std": 0.2, "cv_aoe": 1.0,
             "cv_foe": 2.0, "epoch": 1, "pedestrians": 113, "protocol": "paper"}))
    monkeypatch.setattr(table1, "train", train_small)
    monkeypatch.setattr(table1, "evaluate", evaluate)

    table1.main(["--train", "--scenes", "eth", "--epochs", "1", "--seeds", "1003"])
    workdir = Path("runs") / name
    assert trained == evaluated == [workdir]
    assert [r["epoch"] for r in WorkDir(workdir).read_metrics()] == [1]
    [row] = json.loads((tmp_path / "runs" / "table1" / "table1.json").read_text())
    assert row["aoe"] == 1.5 and row["per_seed"]["1003"]["workdir"] == str(workdir)
    assert json.loads((tmp_path / "results" / "runs" / f"{name}.json").read_text())["aoe"] == 9.0


# docs/reproducing.md: the commands that regenerate the published tables from their records.
PUBLISHED = [
    (table1, ["--seeds", "1000,1001,1002"], "table1"),
    (table1, ["--output", "gaussian", "--seeds", "1000,1001,1002"], "table1_p"),
    (table1, ["--protocol", "loo"], "table1_loo"),
    (crowd, [], "crowd"),
    (crowd, ["--output", "gaussian"], "crowd_p"),
    (schedules, [], "schedules"),
]


@pytest.mark.parametrize("script, flags, stem", PUBLISHED, ids=[p[2] for p in PUBLISHED])
def test_the_published_tables_are_what_their_documented_command_writes(
        script, flags, stem, tmp_path, monkeypatch):
    """`python3 experiments/<script>.py FLAGS --publish`, run on a copy of results/ (from the
    checkout, with its parked runs and without work directories, as after a fresh clone)."""
    copy = tmp_path / "results"
    shutil.copytree(ROOT / "results", copy)
    monkeypatch.setattr(_common, "RESULTS", copy)
    monkeypatch.setattr(schedules, "RESULTS", copy)
    monkeypatch.chdir(ROOT)                          # parked/ as the commands find it
    script.main([*flags, "--publish", "--runs", str(tmp_path / "runs")])
    for suffix in (".md", ".json"):
        assert (copy / f"{stem}{suffix}").read_bytes() == (ROOT / "results" / f"{stem}{suffix}"
                                                           ).read_bytes(), f"{stem}{suffix}"
    assert _contents(copy / "runs") == _contents(ROOT / "results" / "runs")
