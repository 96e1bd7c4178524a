"""Planners in CrowdNav++'s task (gst_jax.simulate.planner, navigation; python -m
gst_jax.navigate): the MPC's choice on a crafted observation, the measures on crafted
episodes, and the command end to end on a few episodes."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gst_jax import navigate
from gst_jax.simulate.environment import REACH_GOAL, COLLISION, EnvParams, Observation
from gst_jax.simulate.navigation import max_steps, navigation_measures
from gst_jax.simulate.planner import SamplingMPC


def _observation(humans, radii=0.0):
    """The robot at the origin heading for (0, 8); humans (H, 1 + P, 2) relative rows."""
    humans = np.asarray(humans, np.float32)
    return Observation(
        robot_node=jnp.array([0.0, 0.0, 0.3, 0.0, 8.0, 1.0, np.pi / 2]),
        temporal_edges=jnp.zeros(2), spatial_edges=jnp.asarray(humans.reshape(len(humans), -1)),
        visible_masks=jnp.ones(len(humans), bool),
        detected_human_num=jnp.asarray(float(len(humans))),
        radii=jnp.full((len(humans), humans.shape[1] - 1), radii))


def test_the_mpc_heads_for_the_goal_and_around_a_predicted_human():
    planner = SamplingMPC()
    far = np.tile([[15.0, 15.0]], (6, 1))
    action, _ = planner(jax.random.key(0), planner.init(), _observation([far]))
    np.testing.assert_allclose(action, [0.0, 1.0], atol=1e-5)      # straight, full speed
    # A human standing 1 m ahead: the plan must keep 0.8 m (+ the radius) from it.
    ahead = np.tile([[0.0, 1.0]], (6, 1))
    for radius in (0.0, 0.3):
        action, state = planner(jax.random.key(0), planner.init(), _observation([ahead], radius))
        path = np.cumsum(np.asarray(state.plan), axis=0) * 0.25
        assert np.all(np.linalg.norm(path - [0.0, 1.0], axis=-1) >= 0.8 + radius - 1e-5)


def test_measures_of_crafted_episodes():
    steps = 5
    robot = np.zeros((2, steps + 1, 2))
    robot[0, :, 1] = np.arange(steps + 1) * 0.25                     # walks 1 m in 4 steps
    robot[0, 5] = robot[0, 4]
    humans = np.full((2, steps + 1, 1, 2), 50.0)
    humans[1, 3, 0] = [0.1, 0.0]                                      # near episode 1's robot
    episodes = {"robot": robot, "humans": humans, "outcome": np.array([REACH_GOAL, COLLISION]),
                "steps": np.array([4, 3]), "radii_mean": np.array([0.1, 0.3])}
    measures = navigation_measures(episodes, EnvParams())
    assert measures["success"] == 0.5 and measures["collision"] == 0.5
    assert measures["navigation_time_s"] == 1.0                      # over the successes
    assert measures["path_length_m"] == 0.5                          # over all episodes
    # Episode 1: steps 0, 1, 2 see the human of step 3 within 5 steps: 3 of 3 steps.
    assert measures["intrusion_ratio"] == 0.5 * (0 + 3 / 3)
    assert max_steps(EnvParams()) == 197                              # CrowdNav++'s timeout


def test_the_command_reports_crowdnavs_measures(tmp_path, capsys):
    navigate.main(["evaluate", "--planner", "cv-mpc", "--episodes", "2", "--plans", "66",
                   "--gif", "1", "--workdir", str(tmp_path), "--json"])
    result = json.loads(capsys.readouterr().out)
    assert result["episodes"] == 2
    assert result["success"] + result["collision"] + result["timeout"] == 1.0
    assert result == json.loads((tmp_path / "cv-mpc-dtaci-seed1000.json").read_text())
    assert (tmp_path / "cv-mpc-dtaci-seed1000-episode0.gif").stat().st_size > 1000


def test_a_ppo_from_rejax_trains_in_the_environment():
    # Only where the rl extra is installed (pip install ".[rl]"); CI installs the test extra.
    pytest.importorskip("rejax")
    import ppo_rejax

    algo, state, _ = ppo_rejax.train("none", humans=2, timesteps=1024, envs=8, steps=32)
    assert int(state.global_step) == 1024
    leaves = jax.tree.leaves(state.actor_ts.params)
    assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in leaves)
    measures = ppo_rejax.measure(algo, state, 2)
    assert measures["success"] + measures["collision"] + measures["timeout"] == 1.0


def test_the_experiment_tabulates_its_records_without_running_them_again(tmp_path, monkeypatch):
    import navigation as experiment

    for planner, regions, humans in experiment.CONFIGURATIONS:
        # Social-force rows with other figures: the reading must leave them out.
        orca = humans == "orca"
        record = {"planner": planner, "regions": regions, "success": 0.9 if orca else 0.5,
                  "collision": 0.1, "timeout": 0.0,
                  "navigation_time_s": 14.0 if regions == "none" else 15.0 if orca else 30.0,
                  "path_length_m": 12.0, "intrusion_ratio": 0.2 if regions == "none" else 0.1,
                  "mean_radius_m": 0.2}
        name = f"{planner}-{regions}{'' if orca else '-' + humans}-seed1000.json"
        (tmp_path / name).write_text(json.dumps(record))
    monkeypatch.setattr("sys.argv", ["navigation.py", "--workdir", str(tmp_path)])
    experiment.main()
    text = (tmp_path / "navigation.md").read_text()
    assert "| sampling MPC | constant velocity | none | ORCA | 0.900 | 0.100 |" in text
    assert "| sampling MPC | constant velocity | DtACI 0.1 | social force | 0.500 |" in text
    assert "four planners' success rates span 0.000" in text
    assert "social-force humans the two planners' success rates (0.500, 0.500)" in text
    assert "change the intrusion ratio by -50 % and the navigation time by +1.0 s" in text
    assert len(json.loads((tmp_path / "navigation.json").read_text())) == 8
