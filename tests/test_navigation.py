"""Planners in CrowdNav++'s task (gst_jax.simulate.crowdnav.planner, navigation; python -m
gst_jax.navigate): the MPC's choice on a crafted observation, the measures on crafted
episodes, and the command end to end on a few episodes."""

import io
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gst_jax import navigate, resources
from gst_jax.conformal import Regions
from gst_jax.data.readers import read_tracks
from gst_jax.errors import DataError, RunError
from gst_jax.progress import Progress
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav import navigation, records
from gst_jax.simulate.crowdnav.crowds import Condition, crowd_rows, person_ids, record_episodes
from gst_jax.simulate.crowdnav.environment import (
    COLLISION,
    CONSTANT_VELOCITY,
    REACH_GOAL,
    SOCIAL_FORCE,
    SPEED_SHIFT,
    TRUTH,
    CrowdNav,
    EnvParams,
    Observation,
    detected_humans,
)
from gst_jax.simulate.crowdnav.navigation import (
    described_run,
    episode_measures,
    max_steps,
    navigation_measures,
    per_episode,
    run_episodes,
)
from gst_jax.simulate.crowdnav.planner import SamplingMPC
from gst_jax.simulate.crowdnav.records import (
    paired_lines,
    record_name,
    row_label,
    same_episodes,
    summary,
)
from gst_jax.testing.drawn import gif_frames, pixels_near


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
                "steps": np.array([4, 3]), "closest_m": np.array([0.7, -0.1]),
                "radii_mean": np.array([0.1, 0.3])}
    measured = episode_measures(episodes, EnvParams())
    measures = navigation_measures(measured, EnvParams())
    assert measures["success"] == 0.5 and measures["collision"] == 0.5
    assert measures["navigation_time_s"] == 1.0                      # over the successes
    assert measures["path_length_m"] == 0.5                          # over all episodes
    # Episode 1: steps 0, 1, 2 see the human of step 3 within 5 steps: 3 of 3 steps.
    assert measures["intrusion_ratio"] == 0.5 * (0 + 3 / 3)
    assert max_steps(EnvParams()) == 197                              # CrowdNav++'s timeout
    assert per_episode(measured, EnvParams()) == {
        "outcome": ["success", "collision"], "time_s": [1.0, 0.75], "closest_m": [0.7, -0.1],
        "intrusion_ratio": [0.0, 1.0]}


def test_the_command_reports_crowdnavs_measures(tmp_path, capsys):
    """JSON, then the table of results/navigation.md; a record per episode count, none
    replaced without --overwrite (refused in one line, before compiling). One program of 2
    episodes (about 30 s to compile here), which the chunk test below takes up again."""
    argv = ["evaluate", "--planner", "cv-mpc", "--plans", "66", "--workdir", str(tmp_path)]
    navigate.main([*argv, "--episodes", "2", "--gif", "1", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert result["episodes"] == 2
    assert result["success"] + result["collision"] + result["timeout"] == 1.0
    record = tmp_path / "cv-mpc-dtaci-episodes2-seed1000.json"
    assert result == json.loads(record.read_text())
    # Episode 0's GIF: a frame per step it lasted, the robot (red) leaving a trail.
    frames = gif_frames(tmp_path / "cv-mpc-dtaci-episodes2-seed1000-episode0.gif")
    assert len(frames) == round(result["per_episode"]["time_s"][0] / 0.25) + 1 > 2
    assert pixels_near(frames[-1], "tab:red", 0.15) > pixels_near(frames[0], "tab:red", 0.15) > 20
    with pytest.raises(SystemExit) as refused:
        navigate.main([*argv, "--episodes", "2", "--alpha", "0.2"])
    assert str(refused.value) == (f"error: {record} exists: a run of the same 2 episodes; "
                                  "--overwrite replaces it, another --workdir keeps it")
    assert json.loads(record.read_text()) == result
    navigate.main([*argv, "--episodes", "3", "--chunk", "2"])
    header, rule, row, footer = capsys.readouterr().out.splitlines()
    assert header == ("| planner | predictions | discs | humans | success | collision | "
                      "timeout | navigation_time_s | path_length_m | intrusion_ratio | "
                      "mean_radius_m |")
    assert rule == "|---" * 11 + "|"
    three = json.loads((tmp_path / "cv-mpc-dtaci-episodes3-seed1000.json").read_text())
    assert row == ("| sampling MPC | constant velocity | DtACI 0.1 | ORCA | " + " | ".join(
        f"{three[c]:.3f}" for c in ("success", "collision", "timeout", "navigation_time_s",
                                    "path_length_m", "intrusion_ratio", "mean_radius_m")) + " |")
    assert footer.startswith("3 episodes of seed 1000; compiling ")
    assert json.loads(record.read_text()) == result


def test_episodes_in_chunks_are_those_of_one_program():
    """--episodes 1000000 ran out of memory: episodes run `chunk` at a time through one
    program (the last chunk padded), each from its own key, so that a chunked run plays
    the episodes of an unchunked one: the same outcomes and steps, positions within
    XLA:CPU's rounding, which the number of lanes changes (by up to 1.4 mm at its default
    level and with the suite's fusion emitters; a lane playing another key would differ by
    metres); progress counts the chunks. The chunks are the command's program above (from
    the persistent cache); one program of 3."""
    env, params = CrowdNav.with_predictor(CONSTANT_VELOCITY, regions=Regions("dtaci", 0.1))
    planner = SamplingMPC(num_plans=66, horizon=env.pred_len, step_s=params.step_s)
    log = io.StringIO()
    chunked, _, _ = run_episodes(env, params, planner, planner.init(), 3, seed=1000, chunk=2,
                                 keep=3, progress=Progress(log))
    whole, _, _ = run_episodes(env, params, planner, planner.init(), 3, seed=1000, keep=3)
    assert chunked.keys() == whole.keys() and whole["humans"].shape == (3, 198, 20, 2)
    for name, array in whole.items():
        if np.issubdtype(array.dtype, np.floating):
            np.testing.assert_allclose(chunked[name], array, rtol=0, atol=2e-3, err_msg=name)
        else:
            np.testing.assert_array_equal(chunked[name], array, err_msg=name)
    assert [line.split(",")[0] for line in log.getvalue().splitlines()] == [
        "episodes 2/3", "episodes 3/3"]


def test_a_chunk_the_memory_cannot_hold_is_refused_with_the_chunk_that_fits(monkeypatch):
    """`navigate --chunk 100000` under a 4 GiB limit hung at 0 % CPU (issue 94): a chunk's
    memory (XLA's estimate of its program) is weighed before it runs. The program of 2
    episodes above (from the persistent cache), with 1 kB left once it is compiled (the
    compiler's own room is tested in test_predict)."""
    env, params = CrowdNav.with_predictor(CONSTANT_VELOCITY, regions=Regions("dtaci", 0.1))
    planner = SamplingMPC(num_plans=66, horizon=env.pred_len, step_s=params.step_s)
    monkeypatch.setattr(navigation, "check_compiler_room", lambda what: None)
    monkeypatch.setattr(resources, "available_memory", lambda device: (1000, "a test's limit"))
    with pytest.raises(DataError, match=r"^2 navigation episodes at once needs \d+ KiB "
                       r"\(XLA's estimate\); 1000 bytes is available \(a test's limit\); use "
                       r"--chunk 1 or less$"):
        run_episodes(env, params, planner, planner.init(), 3, seed=1000, chunk=2)


def test_a_model_of_another_time_step_is_refused(tmp_path):
    """pretrained:zara1_d predicts 0.4 s steps; the task moves in 0.25 s ones."""
    zara = load_model("pretrained:zara1_d")
    with pytest.raises(RunError, match="pretrained:zara1_d predicts steps of 0.4 s, the "
                                       "environment moves in steps of 0.25 s"):
        CrowdNav.with_predictor(zara)
    with pytest.raises(SystemExit, match="^error: pretrained:zara1_d predicts steps of 0.4 s"):
        navigate.main(["evaluate", "--model", "pretrained:zara1_d", "--episodes", "1",
                       "--workdir", str(tmp_path)])


@pytest.mark.parametrize("value", ["0", "1", "-1", "nan", "1.5"])
def test_alpha_outside_0_1_is_refused_when_parsed(value, monkeypatch, capsys):
    """--alpha 1 gave zero-size discs: refused by the parser (status 2, one line)."""
    monkeypatch.setattr(navigate, "navigate", lambda args: pytest.fail(f"ran with {args}"))
    with pytest.raises(SystemExit) as refused:
        navigate.main(["evaluate", "--alpha", value])
    assert refused.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1].endswith(
        f"argument --alpha: must lie strictly between 0 and 1, got {value}")


def test_the_docs_show_the_table_the_command_prints():
    """docs/navigation.md's output block is `summary` of the published record it names."""
    root = Path(__file__).parents[1]
    docs = (root / "docs" / "navigation.md").read_text()
    shown = docs.split("as its published record (results/runs/navigation/) reads:\n\n```\n")[1]
    record = root / "results" / "runs" / "navigation" / "mpc-dtaci-episodes500-seed1000.json"
    assert shown.split("\n```")[0] == summary(json.loads(record.read_text()))


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


def test_the_ppo_learning_curve_continues_from_its_saved_state(tmp_path):
    """--chunk: a point of the curve per chunk, the state saved beside it; a rerun with more
    steps continues from it (the points before are kept, the steps go on)."""
    pytest.importorskip("rejax")
    import ppo_rejax

    settings = dict(predictor="none", humans=2, chunk=1024, envs=8, episodes=2)
    first = ppo_rejax.learning_curve(tmp_path, timesteps=1024, **settings)
    curve = ppo_rejax.learning_curve(tmp_path, timesteps=2048, **settings)
    assert [point["steps"] for point in curve] == [1024, 2048]
    # (as JSON: a policy that never arrives has a NaN navigation time)
    assert json.dumps(curve[0]) == json.dumps(first[0]) and curve[1]["hours"] > curve[0]["hours"]
    assert (tmp_path / "curve.jsonl").read_text().splitlines() == [json.dumps(p) for p in curve]
    assert ppo_rejax.first_reaching([{"success": 0.5}, {"success": 0.91}, {"success": 0.95}]
                                    ) == {"success": 0.91}


def test_the_experiment_tabulates_its_records_without_running_them_again(tmp_path, monkeypatch):
    """Issue 60's records tabulated as before; with --tabulate, issue 75's configurations
    that have no record are listed, not run."""
    import navigation as experiment

    for planner, regions, (humans, *_) in experiment.CONFIGURATIONS:
        # Social-force rows with other figures: the reading must leave them out.
        orca = humans == "orca"
        record = {"planner": planner, "regions": regions, "alpha": 0.1,
                  "model": "pretrained:crowdnav_sj_rand" if planner == "mpc" else None,
                  "success": 0.9 if orca else 0.5,
                  "collision": 0.1, "timeout": 0.0,
                  "navigation_time_s": 14.0 if regions == "none" else 15.0 if orca else 30.0,
                  "path_length_m": 12.0, "intrusion_ratio": 0.2 if regions == "none" else 0.1,
                  "mean_radius_m": 0.2}
        name = f"{planner}-{regions}{'' if orca else '-' + humans}-episodes500-seed1000.json"
        (tmp_path / name).write_text(json.dumps(record))
    monkeypatch.setattr("sys.argv", ["navigation.py", "--workdir", str(tmp_path), "--tabulate"])
    experiment.main()
    text = (tmp_path / "navigation.md").read_text()
    assert "| sampling MPC | constant velocity | none | ORCA | 0.900 | 0.100 |" in text
    assert "| sampling MPC | constant velocity | DtACI 0.1 | social force | 0.500 |" in text
    assert "four planners' success rates span 0.000" in text
    assert "social-force humans the two planners' success rates (0.500, 0.500)" in text
    assert "change the intrusion ratio by -50 % and the navigation time by +1.0 s" in text
    published = json.loads((tmp_path / "navigation.json").read_text())
    assert len(published) == 8 and all(row.get("reactive") is False for row in published[:6])
    # The default scenario's GST and CV rows are issue 60's, in the matrix's table too.
    assert "| 20 ORCA, ignoring the robot | cv | none | 0.900 ± 0.026 |" in text
    missing = len(experiment.MATRIX) - 4 + len(experiment.ISSUE90)     # issue 90's: none run
    assert f"Not yet run ({missing}): truth-mpc dtaci (20 ORCA, ignoring the robot)" in text


def test_the_command_names_each_scenarios_record_and_refuses_a_shift_it_cannot_make(
        tmp_path, monkeypatch):
    """Issue 75's scenarios: every option that changes the humans names the record (runs of
    other settings sit beside each other); a policy shift needs ORCA humans (one line)."""
    seen = {}
    monkeypatch.setattr(navigation, "evaluate", lambda env, params, planner, count, seed, out,
                        described, *rest, **options: seen.update(env=env, **described) or {})
    monkeypatch.setattr(records, "summary", lambda result, out=None: "")
    navigate.main(["evaluate", "--planner", "truth-mpc", "--reactive", "--num-humans", "35",
                   "--shift", "speed", "--workdir", str(tmp_path)])
    env = seen.pop("env")
    assert (env.model, env.num_humans, env.reactive, env.shift) == (TRUTH, 35, True, "speed")
    assert seen["predictor"] == "truth" and seen["model"] is None
    assert record_name("truth-mpc", "dtaci", "orca", 500, 1000, True, 35, "speed") == (
        "truth-mpc-dtaci-reactive-humans35-shiftspeed-episodes500-seed1000")
    assert row_label({**seen, "alpha": 0.1}) == (
        "sampling MPC | truth (the simulator's) | DtACI 0.1 | ORCA, 35 of them, reactive, "
        "shift: speed")
    navigate.main(["evaluate", "--planner", "cv-mpc", "--fresh-tracks", "--regions", "none",
                   "--workdir", str(tmp_path)])
    assert seen.pop("env").fresh_tracks and seen["fresh_tracks"]
    assert record_name("cv-mpc", "none", "orca", 500, 1000, fresh_tracks=True) == (
        "cv-mpc-none-freshtracks-episodes500-seed1000")
    assert row_label({**seen, "alpha": 0.1}) == (
        "sampling MPC | constant velocity, fresh tracks | none | ORCA")
    with pytest.raises(SystemExit, match="^error: --shift policy switches ORCA humans"):
        navigate.main(["evaluate", "--planner", "standing-mpc", "--humans", "social-force",
                       "--shift", "policy", "--workdir", str(tmp_path)])


def test_the_crowds_written_are_the_positions_the_environment_played(tmp_path):
    """Issue 90: `navigate crowds` writes what the task's own humans did. The environment
    replayed step by step from the same keys, with the same planner, gives the positions the
    file holds (read back as any data file is), for the humans the robot detected; a human
    replaced at its goal takes a new id."""
    condition = Condition(SOCIAL_FORCE, reactive=True, num_humans=6, shift=SPEED_SHIFT)
    steps, params = 40, EnvParams(shift_at_s=2.0)
    record = record_episodes(condition, 1, seed=7, params=params, steps=steps)
    ids = person_ids(record["replaced"][0])
    path = tmp_path / "episode.txt"
    path.write_text("\n".join(crowd_rows(record["positions"][0], record["detected"][0], ids)))

    env = CrowdNav(6, CONSTANT_VELOCITY, human_policy=SOCIAL_FORCE, reactive=True,
                   shift=SPEED_SHIFT)
    planner = SamplingMPC(horizon=env.pred_len, step_s=params.step_s)
    reset_key, run_key = jax.random.split(jax.random.split(jax.random.key(7), 1)[0])
    obs, state = env.reset(reset_key, params)
    plan, played, seen = planner.init(), [state.human_position], [detected_humans(state, params)]
    step = jax.jit(lambda key, state, action: env.step_env(key, state, action, params))
    for key in jax.random.split(run_key, steps):
        plan_key, env_key = jax.random.split(key)
        action, plan = planner(plan_key, plan, obs)
        obs, state, *_ = step(env_key, state, action)
        played.append(state.human_position)
        seen.append(detected_humans(state, params))
    played, seen = np.asarray(played), np.asarray(seen)

    np.testing.assert_allclose(record["positions"][0], played, atol=1e-5)
    np.testing.assert_array_equal(record["detected"][0], seen)
    tracks = read_tracks(path)
    rows = {(int(f), int(p)): xy for f, p, xy in zip(tracks.frames, tracks.pedestrians,
                                                    tracks.xy)}
    expected = {(t, int(ids[t, k])): played[t, k] for t, k in zip(*np.nonzero(seen))}
    assert rows.keys() == expected.keys() and len(rows) > steps
    for key, xy in expected.items():
        np.testing.assert_allclose(rows[key], xy, atol=1e-4)
    assert (np.diff(ids, axis=0) != 0).sum() == record["replaced"][0].sum()


def test_evaluate_prints_its_paired_differences_from_the_records_of_the_same_episodes(tmp_path):
    """Issue 90: the other settings' records of the same episodes in the folder are compared
    episode by episode; records of other episodes (another scenario) are not."""
    def record(planner, regions, outcomes, shift="none"):
        fields = described_run(planner, regions, shift=shift)
        return {**fields, "seed": 1000, "episodes": len(outcomes), "success": 0.0,
                "per_episode": {"outcome": outcomes, "time_s": [10.0] * len(outcomes),
                                "closest_m": [0.2] * len(outcomes),
                                "intrusion_ratio": [0.1] * len(outcomes)}}
    s, c = "success", "collision"
    cv = record("cv-mpc", "none", [s] * 8 + [c] * 2)
    truth = record("truth-mpc", "none", [s] * 10)
    shifted = record("cv-mpc", "dtaci", [c] * 10, shift="speed")
    for name, other in [("truth", truth), ("shifted", shifted)]:
        (tmp_path / f"{name}.json").write_text(json.dumps(other))
    assert same_episodes(cv, tmp_path) == [truth]
    lines = paired_lines(cv, same_episodes(cv, tmp_path))
    assert lines[1].startswith("  success - truth + no discs: -0.200 (")
    assert lines[1].endswith("p 0.5 (0 / 2)")
