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
from gst_jax.config import ModelConfig, TimeGrid
from gst_jax.data.batch import SceneBatch
from gst_jax.model import Controls, init_params
from gst_jax.rollout import rollout
from gst_jax.simulate.__main__ import main as simulate_main


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
    config = ModelConfig()
    params = init_params(config, jax.random.key(0))
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
    full = rollout(params, jax.random.key(2), batch, config, Controls.make(0.03, 1, True),
                   hard=True, deterministic=True)
    np.testing.assert_allclose(model(history, np.ones((8, 2)), jax.random.key(2)),
                               full.displacements[0, 0], atol=1e-6)


def test_command_runs_a_shipped_model_and_writes_measures_and_figures(tmp_path, capsys):
    simulate_main(["pretrained:eth", "--scenario", "a", "--animate", "--workdir", str(tmp_path),
                   "--json"])
    rows = json.loads((tmp_path / "results.json").read_text())
    assert [row["model"] for row in rows] == ["constant velocity", "pretrained:eth n=1"]
    assert json.loads(capsys.readouterr().out) == rows
    for row in rows:
        assert row["scenario"] == "a_late_crossing" and row["min_distance_m"] > 0
        assert Path(row["figure"]).stat().st_size > 5_000
        with PIL.Image.open(row["animation"]) as gif:   # one frame per simulated step
            assert (gif.format, gif.n_frames) == ("GIF", simulate.late_crossing().steps + 1)
