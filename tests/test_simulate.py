"""Closed-loop simulation: scenarios, kinematics (constant-velocity model), detectors."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
import PIL.Image
import pytest

from gst_jax import simulate
from gst_jax.config import EVAL_TAU, ModelConfig, TimeGrid
from gst_jax.data.batch import SceneBatch
from gst_jax.model import Controls, init_params
from gst_jax.rollout import rollout
from gst_jax.runs import load_model
from gst_jax.simulate.__main__ import main as simulate_main
from gst_jax.simulate.paper import encounters, loop
from gst_jax.testing.drawn import (
    bar_heights,
    bar_intervals,
    gif_frames,
    line_data,
    pixels_near,
    saved_figures,
)


@pytest.mark.parametrize("name", list(simulate.SCENARIOS))
def test_scenarios_build_valid_initial_states(name):
    scenario = simulate.SCENARIOS[name](TimeGrid())
    agents = scenario.start.shape[0]
    assert scenario.start.shape == scenario.velocity.shape == (agents, 2) and agents >= 2
    assert scenario.detected_from.shape == (agents,) and scenario.detected_from[0] == 0
    assert np.all(scenario.detected_from >= 0) and np.all(np.isfinite(scenario.start))
    assert np.linalg.norm(scenario.goal - scenario.start[0]) > 1.0
    gaps = np.linalg.norm(scenario.start[:, None] - scenario.start[None], axis=-1)
    assert gaps[~np.eye(agents, dtype=bool)].min() > simulate.ROBOT_COLLISION_DISTANCE


def test_constant_velocity_model_moves_every_agent_in_a_straight_line():
    scenario = simulate.intersection()
    positions = np.asarray(simulate.simulate(simulate.constant_velocity_model, scenario,
                                             jax.random.key(0)))
    steps = np.arange(scenario.steps + 1)[:, None, None]
    expected = scenario.start[None] + scenario.velocity[None] * scenario.grid.step_s * steps
    np.testing.assert_allclose(positions, expected, atol=1e-4)
    result = simulate.robot_measures(positions, scenario)
    assert not result["freezing_or_u_turn"] and abs(result["path_length_ratio"] - 1) < 1e-4


def test_u_turn_and_freezing_detectors():
    goal = np.array([10.0, 0.0])
    straight = np.stack([np.linspace(0, 10, 26), np.zeros(26)], -1)
    assert not simulate.freezing_or_u_turn(straight, goal, 0.4)["freezing_or_u_turn"]
    out_and_back = np.concatenate([straight[:10], straight[9::-1]])
    assert simulate.freezing_or_u_turn(out_and_back, goal, 0.4)["u_turn"]
    stop = np.concatenate([straight[:5], np.repeat(straight[5:6], 8, axis=0), straight[5:]])
    detected = simulate.freezing_or_u_turn(stop, goal, 0.4)
    assert detected["frozen"] and not detected["u_turn"]


def test_gst_drives_the_loop_without_nan():
    config = ModelConfig(encoder_layers=1)  # depth changes nothing here; three compile longer
    params = jax.jit(init_params, static_argnums=0)(config, jax.random.key(0))
    model = simulate.gst_model(params, config, Controls.make(0.03, 1, True))
    scenario = dataclasses.replace(simulate.late_crossing(), duration_s=6 * 0.4)
    positions = np.asarray(simulate.simulate(model, scenario, jax.random.key(1)))
    assert positions.shape == (7, 2, 2) and np.all(np.isfinite(positions))
    # The undetected human walks its script until detection (step 4).
    np.testing.assert_allclose(positions[:5, 1], scenario.start[1] + scenario.velocity[1]
                               * scenario.grid.step_s * np.arange(5)[:, None], atol=1e-5)
    # The model's step is the first displacement of a full 12-step rollout.
    history = np.cumsum(np.full((8, 2, 2), 0.4), axis=0) + np.array([[0.0, 0.0], [0.0, 2.0]])
    batch = SceneBatch(positions=np.concatenate([history, np.zeros((12, 2, 2))])[None],
                       position_mask=np.repeat([1.0, 0.0], [8, 12])[None, :, None] * np.ones(2),
                       node_mask=np.repeat([1.0, 0.0], [8, 12])[None, :, None] * np.ones(2),
                       scene_mask=np.ones(1), window_index=np.zeros(1, np.int32))
    full = jax.jit(lambda key: rollout(params, key, batch, config, Controls.make(0.03, 1, True),
                                       hard=True, deterministic=True))(jax.random.key(2))
    np.testing.assert_allclose(jax.jit(model)(history, np.ones((8, 2)), jax.random.key(2)),
                               full.displacements[0, 0], atol=1e-6)


def test_command_runs_a_shipped_model_and_writes_measures_and_figures(tmp_path, capsys):
    """Per model, its measures, a figure of every agent's path from the scenario's start
    (constant velocity's robot walks its straight line) and an animation of every step."""
    with saved_figures() as saved:
        simulate_main(["pretrained:eth", "--scenario", "a", "--animate", "--workdir",
                       str(tmp_path), "--json"])
    rows = json.loads((tmp_path / "results.json").read_text())
    assert [row["model"] for row in rows] == ["constant velocity", "pretrained:eth n=1"]
    assert json.loads(capsys.readouterr().out) == rows
    scenario = simulate.late_crossing()
    straight = scenario.start[0] + (scenario.velocity[0] * scenario.grid.step_s
                                    * np.arange(scenario.steps + 1)[:, None])
    for row in rows:
        assert row["scenario"] == "a_late_crossing" and row["min_distance_m"] > 0
        # Each agent's whole path first (dotted), the robot's in red, then the robot's goal.
        paths = saved[Path(row["figure"])].axes[0]
        robot, human = line_data(paths, "tab:red")[0], line_data(paths, "tab:blue")[0]
        for path, start in ((robot, scenario.start[0]), (human, scenario.start[1])):
            assert path.shape == (scenario.steps + 1, 2) and np.isfinite(path).all()
            np.testing.assert_allclose(path[0], start, atol=1e-5)
        np.testing.assert_allclose(line_data(paths, "tab:red")[-1], [scenario.goal])
        if row["model"] == "constant velocity":
            np.testing.assert_allclose(robot, straight, atol=1e-4)
        assert pixels_near(row["figure"], "tab:red") > 500      # legend and goal alone: 237
        with PIL.Image.open(row["animation"]) as gif:   # one frame per simulated step
            assert (gif.format, gif.n_frames) == ("GIF", scenario.steps + 1)
        frames = gif_frames(row["animation"])           # the robot's trail grows
        assert pixels_near(frames[-1], "tab:red", 0.15) > pixels_near(frames[0], "tab:red", 0.15)


def test_the_papers_scenarios_run_with_crowdnavs_reactive_orca_humans(capsys, tmp_path):
    """One core moves both simulators' agents: in each of the paper's scenarios a robot that
    walks straight on (constant velocity) meets people who, as ORCA humans, give way to it
    (never closer than their two radii), where people moved by the model as the robot do not
    in the intersection; the robot's own path is the model's either way."""
    closest = {}
    for name, make in simulate.SCENARIOS.items():
        scenario = make()
        for humans in (simulate.MODEL_HUMANS, simulate.ORCA_HUMANS):
            positions = np.asarray(simulate.simulate(simulate.constant_velocity_model,
                                                     scenario, jax.random.key(0), humans))
            steps = np.arange(scenario.steps + 1)[:, None]
            np.testing.assert_allclose(positions[:, 0], scenario.start[0] + scenario.velocity[0]
                                       * scenario.grid.step_s * steps, atol=1e-4)
            closest[name, humans] = np.linalg.norm(positions[:, 1:] - positions[:, :1],
                                                   axis=-1).min()
        assert closest[name, simulate.ORCA_HUMANS] >= 2 * loop.ORCA_RADIUS - 0.02
    assert closest["c", simulate.MODEL_HUMANS] < 0.5
    # In random encounters (groups that start closer than their ORCA radii allow) no one comes
    # within the collision distance of the robot, where people moved by the model often do.
    episodes = encounters.sample_encounters(20, seed=2)
    people = np.arange(11)[None, None, 1:] <= episodes.people[:, None, None]
    hits = {}
    for humans in (simulate.MODEL_HUMANS, simulate.ORCA_HUMANS):
        positions, _, _ = encounters.run_encounters(simulate.constant_velocity_model, episodes,
                                                    jax.random.key(0), humans)
        gaps = np.linalg.norm(positions[:, :, 1:] - positions[:, :, :1], axis=-1)
        hits[humans] = int(np.sum(np.where(people, gaps, np.inf).min(axis=(1, 2))
                                  < simulate.ROBOT_COLLISION_DISTANCE))
    assert hits[simulate.ORCA_HUMANS] == 0 and hits[simulate.MODEL_HUMANS] >= 5
    simulate_main(["--scenario", "c", "--humans", "orca", "--workdir", str(tmp_path), "--json"])
    [row] = json.loads(capsys.readouterr().out)
    assert row["min_distance_m"] == pytest.approx(closest["c", simulate.ORCA_HUMANS], abs=1e-4)
    with pytest.raises(ValueError, match="humans must be"):
        loop.episode(simulate.constant_velocity_model, *(np.zeros((2, 2)),) * 2, np.zeros(2),
                     jax.random.key(0), steps=1, obs_len=8, step_s=0.4, humans="walls")


def test_random_encounters_are_reproducible_and_their_empty_slots_never_seen():
    first = encounters.sample_encounters(40, seed=3)
    again = encounters.sample_encounters(40, seed=3)
    np.testing.assert_array_equal(first.start, again.start)
    assert set(first.people.tolist()) <= set(range(2, 11)) and len(set(first.kind)) == 4
    empty = np.arange(11)[None] > first.people[:, None]
    assert np.all(first.detected_from[empty] > first.steps)
    assert np.all(np.abs(first.start[empty]) >= 1e3)
    late = first.kind == encounters.KINDS.index("late")
    people = ~empty & (np.arange(11)[None] > 0)
    assert np.all(first.detected_from[late[:, None] & people] >= round(1 / 0.4))
    assert np.all(first.detected_from[~late[:, None] & people] == 0)


def test_encounters_run_as_one_program_equal_each_episode_simulated_alone():
    """Constant velocity ignores everyone: the robot walks straight and arrives after 9.6 s
    (within 0.5 m of its goal 12 m away at 1.2 m/s, 0.4 s steps); GST on a batch of
    encounters moves everyone as `simulate` does on each episode's own agents."""
    episodes = encounters.sample_encounters(3, seed=1)
    positions, _, _ = encounters.run_encounters(simulate.constant_velocity_model, episodes,
                                                jax.random.key(0))
    summary = encounters.summarize(encounters.episode_measures(positions, episodes))
    assert summary["arrived"][0] == 1 and summary["time_to_goal_s"][0] == pytest.approx(9.6)
    assert summary["freezing_or_u_turn"][0] == 0
    run = load_model("pretrained:eth_d")
    config = run.model_config
    model = simulate.gst_model(run.params, config,
                               Controls.make(EVAL_TAU, config.num_edge_heads, config.ghost))
    batched, _, _ = encounters.run_encounters(model, episodes, jax.random.key(0))
    keys = jax.random.split(jax.random.key(0), 3)
    agents = 1 + int(episodes.people[0])
    alone = np.asarray(simulate.simulate(model, episodes.scenario(0), keys[0]))
    np.testing.assert_allclose(batched[0, :, :agents], alone, atol=1e-4)


def test_the_encounter_study_pairs_each_sparse_member_with_its_full_connection(tmp_path):
    """experiments/encounters.py: finished members by label, and the paired difference of
    freezing rates on the same episodes with its interval."""
    from encounters import members, paired_difference

    for name, finished in [("n16-partial-seed1000", True), ("n0-partial-seed1000", True),
                           ("n4-partial-seed1000", True), ("n16-full-seed1001", False)]:
        (tmp_path / name / "eval").mkdir(parents=True)
        if finished:
            (tmp_path / name / "eval" / "test.json").write_text("{}")
    assert list(members(tmp_path)) == ["n=F partial 1000", "n=4 partial 1000",
                                       "n=16 partial 1000"]
    sparse = np.array([1, 0, 0, 0, 1, 0, 0, 0], bool)
    full = np.array([1, 1, 1, 0, 1, 1, 0, 0], bool)
    difference, low, high = paired_difference(sparse, full)
    assert difference == pytest.approx(-3 / 8) and low < difference < high
    assert paired_difference(full, full) == (0.0, 0.0, 0.0)


def _froze_in(flags: str) -> dict:
    """A model's summary over episodes that froze where `flags` says '1'."""
    from gst_jax.simulate.paper.encounters import summarize
    rows = [{"freezing_or_u_turn": f == "1", "frozen": f == "1", "u_turn": False,
             "collided": False, "arrived": f == "0", "time_to_goal_s": 9.0, "progress": 1.0,
             "path_length_ratio": 1.1} for f in flags]
    return {**summarize(rows), "compile_s": 1.0, "run_s": 1.0, "episodes_per_s": 4.0}, rows


def test_the_members_of_an_earlier_record_keep_their_rates_and_pairs(tmp_path, monkeypatch):
    """experiments/encounters.py where the work directories of earlier members are gone:
    they keep their published rates and pairs; a new member pairs episode by episode with a
    full connection recorded per episode, and with one whose episodes were lost through the
    widest interval the two rates allow."""
    import encounters

    study = tmp_path / "eth"
    for name in ("n4-partial-seed1001", "n16-partial-seed1000"):
        (study / name / "eval").mkdir(parents=True)
        (study / name / "eval" / "test.json").write_text("{}")
    earlier = {"n=F partial 1000": "0110", "n=F partial 1001": "1100", "n=4 partial 1000": "0100"}
    out = tmp_path / "out"
    out.mkdir()
    published_pair = {"sparse": "n=4 partial 1000", "full": "n=F partial 1000",
                      "freezing_difference": [-0.25, -0.7, 0.2]}
    (out / "encounters.json").write_text(json.dumps({
        "episodes": 4, "seed": 0, "scene": "eth", "members": list(earlier),
        "models": {label: _froze_in(flags)[0] for label, flags in
                   {"constant velocity": "0000", **earlier, "crowd_d": "0000"}.items()},
        "pairs": [published_pair], "froze": {"n=F partial 1001": "1100"}}))
    now = {"constant velocity": "0001", "n=4 partial 1001": "1000", "n=16 partial 1000": "1010",
           "crowd_d": "0011"}

    def simulated(models, count, out, **_):
        assert count == 4 and [label for label, _ in models] == list(now)
        return ({label: _froze_in(now[label])[0] for label, _ in models},
                {label: _froze_in(now[label])[1] for label, _ in models})

    monkeypatch.setattr(encounters, "load_model", lambda spec: spec)
    monkeypatch.setattr(encounters, "step_models", lambda runs: [(None, runs[0])])
    monkeypatch.setattr(encounters, "time_grid", lambda runs: None)
    monkeypatch.setattr(encounters, "run_encounter_study", simulated)
    with saved_figures() as saved:
        encounters.main(["--study", str(study), "--episodes", "4", "--workdir", str(out)])

    record = json.loads((out / "encounters.json").read_text())
    assert record["members"] == ["n=F partial 1000", "n=F partial 1001", "n=4 partial 1000",
                                 "n=4 partial 1001", "n=16 partial 1000"]
    assert list(record["models"]) == ["constant velocity", *record["members"], "crowd_d"]
    assert record["models"]["n=F partial 1000"]["freezing_or_u_turn"][0] == 0.5
    assert record["froze"] == {"n=4 partial 1001": "1000", "n=16 partial 1000": "1010",
                               "n=F partial 1001": "1100"}
    pairs = {pair["sparse"]: pair for pair in record["pairs"]}
    assert pairs["n=4 partial 1000"] == published_pair
    assert pairs["n=4 partial 1001"]["freezing_difference"] == pytest.approx(
        encounters.paired_difference(np.array([1, 0, 0, 0], bool), np.array([1, 1, 0, 0], bool)))
    lost = pairs["n=16 partial 1000"]       # 2 froze against 2, at most 0 of them shared
    assert lost["paired"] is False and lost["freezing_difference"] == pytest.approx(
        encounters.paired_difference(np.array([1, 1, 0, 0], bool), np.array([0, 0, 1, 1], bool)))
    assert "| n=16 partial 1000 | n=F partial 1000 | +0.000 [-0.980, +0.980] * |" in (
        out / "encounters.md").read_text()
    # The figure: every model's rates, those kept and those simulated now (froze: red; none
    # collided: blue bars of height 0).
    rates = saved[out / "encounters.png"].axes[0]
    assert [label.get_text() for label in rates.get_xticklabels()] == list(record["models"])
    froze, collided = bar_heights(rates)
    np.testing.assert_allclose(froze, [0.25, 0.5, 0.5, 0.25, 0.25, 0.5, 0.5])
    np.testing.assert_allclose(collided, 0)
    assert pixels_near(out / "encounters.png", "tab:red") > 1_000


def test_a_models_stored_encounters_are_read_back_not_simulated_again(tmp_path):
    """run_encounter_study(stored=...): the first call simulates and keeps the measures; the
    second reads them (a model that cannot run proves nothing was simulated); other episodes
    (another count) are simulated anew."""
    from gst_jax.simulate.paper.study import run_encounter_study

    stored = {"cv": tmp_path / "cv.json"}
    first, rows = run_encounter_study([("cv", simulate.constant_velocity_model)], 6,
                                      tmp_path / "a", stored=stored)

    def cannot_run(*args):
        raise AssertionError("simulated although stored")

    again, rows_again = run_encounter_study([("cv", cannot_run)], 6, tmp_path / "b",
                                            stored=stored)
    assert json.loads(json.dumps(first)) == again and json.loads(json.dumps(rows)) == rows_again
    with pytest.raises(AssertionError, match="simulated although stored"):
        run_encounter_study([("cv", cannot_run)], 7, tmp_path / "c", stored=stored)


def test_the_encounter_command_writes_rates_and_their_figure(tmp_path, capsys):
    """Constant velocity over 12 random encounters: it always arrives; the figure draws the
    rates it printed (of 12 episodes) for freezing or turning back and for collisions, each
    with its 95 % interval."""
    with saved_figures() as saved:
        simulate_main(["--encounters", "12", "--workdir", str(tmp_path), "--json"])
    rates = json.loads(capsys.readouterr().out)["constant velocity"]
    assert rates["episodes"] == 12 and rates["arrived"][0] == 1.0
    record = json.loads((tmp_path / "encounters.json").read_text())
    assert record["episodes"] == 12
    drawn = saved[tmp_path / "encounters.png"].axes[0]
    assert [label.get_text() for label in drawn.get_xticklabels()] == ["constant velocity"]
    for heights, interval, key in zip(bar_heights(drawn), bar_intervals(drawn),
                                      ("freezing_or_u_turn", "collided")):
        rate, low, high = rates[key]
        assert 0 <= low <= rate <= high <= 1 and 12 * rate == pytest.approx(round(12 * rate))
        np.testing.assert_allclose(heights, [rate])
        np.testing.assert_allclose(interval, [[low, high]])
