"""CrowdNav++'s task as a jittable environment (gst_jax.simulate.crowdnav.environment): its rules on
cases derived from CrowdNav++'s code (crowd_sim_var_num.py's calc_reward and reset,
crowd_sim.py's detect_visible, vec_pretext_normalize.py's prediction penalty)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gst_jax.conformal import Regions
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav import environment
from gst_jax.simulate.crowdnav.environment import (
    COLLISION,
    DISCOMFORT,
    NOTHING,
    REACH_GOAL,
    TIMEOUT,
    CrowdNav,
    EnvParams,
)
from gst_jax.stream import StreamModel

ENV = CrowdNav(num_humans=4)
RESET = jax.jit(ENV.reset)
PARAMS = EnvParams()
FAR = 100.0


@pytest.fixture(scope="module")
def step_env():
    return jax.jit(ENV.step_env)


def _state(robot=(0.0, 0.0), goal=(0.0, 8.0), humans=(), radius=0.3, time=0.0, potential=None):
    """A state with the robot at rest at `robot` and the listed humans (the others far away),
    all at rest and heading for where they stand."""
    _, state = RESET(jax.random.key(0), PARAMS)
    position = np.full((ENV.num_humans, 2), FAR) + np.arange(ENV.num_humans)[:, None] * 10
    position[:len(humans)] = np.reshape(humans, (-1, 2))
    robot, goal = jnp.asarray(robot, jnp.float32), jnp.asarray(goal, jnp.float32)
    return state.replace(
        robot_position=robot, robot_velocity=jnp.zeros(2), robot_goal=goal,
        human_position=jnp.asarray(position, jnp.float32),
        human_velocity=jnp.zeros((ENV.num_humans, 2)),
        human_goal=jnp.asarray(position, jnp.float32),
        human_radius=jnp.full(ENV.num_humans, radius), time=jnp.asarray(time, jnp.float32),
        potential=-jnp.linalg.norm(robot - goal) if potential is None else jnp.asarray(potential),
        tracks=state.tracks.replace(positions=jnp.zeros_like(state.tracks.positions),
                                    detected=jnp.zeros_like(state.tracks.detected)))


def test_the_robot_detects_a_human_whose_surface_is_within_5_m_in_any_direction():
    def seen(x, radius=0.3, fov=PARAMS.fov):
        state = _state(humans=[(x, 0.0)], radius=radius).replace(robot_velocity=jnp.array([1.0, 0]))
        return bool(environment.detected_humans(state, PARAMS.replace(fov=fov))[0])

    assert seen(5.6) and not seen(5.61)                 # 5.6 - 0.3 - 0.3 = 5.0: inclusive
    assert seen(5.8, radius=0.5) and not seen(5.81, radius=0.5)
    assert seen(-3.0)                                    # behind the robot's motion: 360 degrees
    assert not seen(-3.0, fov=np.pi) and seen(3.0, fov=np.pi)
    assert not seen(0.0)                                 # at its centre: CrowdNav++'s NaN angle


def test_undetected_humans_are_15_and_the_rows_sorted_nearest_first():
    state = environment._observed(_state(humans=[(3.0, 0.0), (0.0, 1.0), (20.0, 0.0)]), PARAMS)
    obs = ENV._observation(jax.random.key(0), state, PARAMS)[0]
    np.testing.assert_array_equal(obs.visible_masks, [True, True, False, False])
    np.testing.assert_allclose(obs.spatial_edges[0], np.tile([0.0, 1.0], 6))
    np.testing.assert_allclose(obs.spatial_edges[1], np.tile([3.0, 0.0], 6))
    np.testing.assert_allclose(obs.spatial_edges[2:], 15.0)
    assert float(obs.detected_human_num) == 2
    alone = environment._observed(_state(), PARAMS)
    assert float(ENV._observation(jax.random.key(0), alone, PARAMS)[0].detected_human_num) == 1


@pytest.mark.parametrize("distance, reward, outcome, done", [
    (0.59, -20.0, COLLISION, True),           # centres closer than 0.3 + 0.3
    (0.60, -0.625, DISCOMFORT, False),        # touching: 2.5 (0 - 0.25)
    (0.65, -0.5, DISCOMFORT, False),          # 0.05 m apart: 2.5 (0.05 - 0.25)
])
def test_collision_and_discomfort_are_judged_before_the_move(step_env, distance, reward,
                                                               outcome, done):
    state = _state(humans=[(distance, 0.0)], potential=-123.0)
    # Moving away does not help: the reward is on the state before the step's move.
    _, after, got, finished, info = step_env(jax.random.key(1), state, jnp.array([-1.0, 0]),
                                             PARAMS)
    assert float(got) == pytest.approx(reward) and bool(finished) == done
    assert int(info["outcome"]) == outcome
    assert float(after.potential) == -123.0            # discomfort leaves the potential alone


def test_arrival_within_the_robots_radius_and_progress_rewarded_a_step_late(step_env):
    at_goal = _state(robot=(0.0, 7.71))
    _, _, reward, done, info = step_env(jax.random.key(1), at_goal, jnp.zeros(2), PARAMS)
    assert float(reward) == 10.0 and bool(done) and int(info["outcome"]) == REACH_GOAL
    short = _state(robot=(0.0, 7.69))
    _, _, _, done, info = step_env(jax.random.key(1), short, jnp.zeros(2), PARAMS)
    assert not bool(done) and int(info["outcome"]) == NOTHING
    # 0.25 m towards the goal: nothing on the step that moves, 2 x 0.25 on the next.
    state = _state()
    _, state, first, _, _ = step_env(jax.random.key(1), state, jnp.array([0.0, 1.0]), PARAMS)
    _, state, second, _, _ = step_env(jax.random.key(2), state, jnp.zeros(2), PARAMS)
    assert float(first) == pytest.approx(0.0, abs=1e-6)
    assert float(second) == pytest.approx(0.5, abs=1e-5)


def test_the_action_is_scaled_to_the_robots_speed(step_env):
    _, state, _, _, _ = step_env(jax.random.key(1), _state(), jnp.array([3.0, 4.0]), PARAMS)
    np.testing.assert_allclose(state.robot_position, [0.15, 0.2], atol=1e-6)
    np.testing.assert_allclose(state.robot_velocity, [0.6, 0.8], atol=1e-6)


def test_timeout_after_49_s_comes_before_a_collision(step_env):
    state = _state(humans=[(0.3, 0.0)], time=49.0)
    _, _, reward, done, info = step_env(jax.random.key(1), state, jnp.zeros(2), PARAMS)
    assert float(reward) == 0.0 and bool(done) and int(info["outcome"]) == TIMEOUT
    state = _state(time=48.75)
    assert not bool(step_env(jax.random.key(1), state, jnp.zeros(2), PARAMS)[3])


def test_the_prediction_penalty_is_the_worst_predicted_step_within_06_m():
    robot = _state()
    futures = jnp.full((ENV.num_humans, 5, 2), FAR)
    predicted = jnp.array([True, True, False, False])

    def penalty(hits):  # hits: {(human, step k from 1)}
        f = futures
        for human, k in hits:
            f = f.at[human, k - 1].set(jnp.array([0.55, 0.0]))
        return float(environment._prediction_penalty(robot, f, predicted, PARAMS))

    assert penalty([]) == 0.0
    assert penalty([(0, 1)]) == -5.0
    assert penalty([(1, 3)]) == -1.25
    assert penalty([(0, 3), (1, 1)]) == -5.0
    assert penalty([(2, 1)]) == 0.0                      # not predicted now: no penalty


def test_episodes_start_as_crowdnav_places_robot_and_humans():
    env = CrowdNav()
    starts = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(
        jax.random.split(jax.random.key(3), 16), PARAMS)[1]
    robot, goal = np.asarray(starts.robot_position), np.asarray(starts.robot_goal)
    assert np.all(np.linalg.norm(robot - goal, axis=-1) >= 8.0)
    assert np.all(np.abs(robot) <= 6) and np.all(np.abs(goal) <= 6)
    human, human_goal = np.asarray(starts.human_position), np.asarray(starts.human_goal)
    radius = np.asarray(starts.human_radius)
    np.testing.assert_allclose(human_goal, -human)
    assert np.all((radius >= 0.3) & (radius <= 0.5))
    speed = np.asarray(starts.human_v_pref)
    assert np.all((speed >= 0.5) & (speed <= 1.5))
    # Shifted off the circle of 6 sqrt 2 by U(0, 2) per axis.
    on_circle = np.linalg.norm(human - 1.0, axis=-1)
    assert np.all(np.abs(on_circle - 6 * np.sqrt(2)) <= np.sqrt(2) + 1e-5)
    # Every start clear of earlier agents' positions and goals by both radii + 0.25.
    for e in range(16):
        for i in range(env.num_humans):
            for j in range(i):
                need = radius[e, i] + radius[e, j] + 0.25 - 1e-5
                assert np.linalg.norm(human[e, i] - human[e, j]) >= need
                assert np.linalg.norm(human[e, i] - human_goal[e, j]) >= need
            need = radius[e, i] + 0.3 + 0.25 - 1e-5
            assert np.linalg.norm(human[e, i] - robot[e]) >= need
            assert np.linalg.norm(human[e, i] - goal[e]) >= need


def test_humans_walk_at_1_m_s_capped_by_their_speed_change_goals_every_5_s_and_respawn(
        step_env):
    state = _state(humans=[(0.0, 20.0), (30.0, 0.0)]).replace(
        human_goal=jnp.array([[10.0, 20.0], [30.3, 0.0]] + [[FAR, FAR]] * 2),
        human_v_pref=jnp.array([0.6, 1.3, 1.0, 1.0]))
    velocity = ENV.human_velocities(state, PARAMS)
    np.testing.assert_allclose(velocity[0], [0.6, 0.0], atol=1e-5)   # 1 m/s capped at 0.6
    np.testing.assert_allclose(velocity[1], [0.3, 0.0], atol=1e-5)   # within 1 m: the offset
    # Goals change only on steps that end a multiple of 5 s.
    changed = []
    for steps in (19, 20):
        after = environment._new_goals(jax.random.key(5), state.replace(
            steps=jnp.asarray(steps)), PARAMS.replace(goal_change_chance=1.0))
        changed.append(bool(np.any(np.asarray(after.human_goal) != np.asarray(state.human_goal))))
    assert changed == [False, True]
    # Human 1 is 0.25 m from its goal, within its radius, after a step: a new human.
    _, after, _, _, _ = step_env(jax.random.key(1), state, jnp.zeros(2), PARAMS)
    assert np.linalg.norm(np.asarray(after.human_position[1]) - [30.0, 0.0]) > 5
    np.testing.assert_allclose(after.human_goal[1], -after.human_position[1])


@pytest.mark.parametrize("fresh_tracks", [False, True])
def test_a_replaced_human_keeps_its_slots_history_unless_tracks_start_fresh(fresh_tracks):
    """CrowdNav++ gives a replaced human its predecessor's slot and history, so that a
    predictor sees one track jump across the scene; with fresh_tracks the slot's history
    starts empty, as a tracker's new identity would."""
    env = CrowdNav(4, environment.CONSTANT_VELOCITY, fresh_tracks=fresh_tracks)
    state = _state(humans=[(2.0, 0.0)]).replace(
        human_goal=jnp.array([[2.2, 0.0]] + [[FAR, FAR]] * 3), human_v_pref=jnp.ones(4))
    step = jax.jit(env.step_env)
    _, state, _, _, info = step(jax.random.key(0), state, jnp.zeros(2), PARAMS)
    assert bool(info["replaced"][0]) and not np.asarray(info["replaced"][1:]).any()
    history = np.asarray(state.tracks.detected[0])
    assert history.sum() == (0 if fresh_tracks else 1)      # the predecessor, seen once
    np.testing.assert_array_equal(state.tracks.detected[1:], 0)


def test_social_force_humans_follow_crowdnavs_formula():
    # crowd_nav/policy/social_force.py with A = 2, B = 1, KI = 1, one 0.25 s step.
    env = CrowdNav(num_humans=4, human_policy=environment.SOCIAL_FORCE)
    state = _state(humans=[(-0.5, 0.0), (0.5, 0.0), (0.0, 20.0), (0.0, 40.0)]).replace(
        human_goal=jnp.array([[4.0, 0.0], [-4.0, 0.0], [4.0, 20.0], [4.0, 40.0]]),
        human_velocity=jnp.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]),
        human_v_pref=jnp.array([1.0, 1.0, 1.0, 0.5]))
    velocity = np.asarray(env.human_velocities(state, PARAMS))
    # Face to face 1 m apart (radii 0.3): pulled on at 1 (1 - 0), pushed back at
    # 2 exp(0.6 - 1) = 1.3406.
    push = 2 * np.exp(0.6 - 1.0)
    np.testing.assert_allclose(velocity[0], [(1.0 - push) * 0.25, 0.0], atol=1e-5)
    np.testing.assert_allclose(velocity[1], [-(1.0 - push) * 0.25, 0.0], atol=1e-5)
    np.testing.assert_allclose(velocity[2], [1.0, 0.0], atol=1e-5)    # already at v_pref
    np.testing.assert_allclose(velocity[3], [0.5, 0.0], atol=1e-5)    # 1.625 capped at 0.5
    with pytest.raises(ValueError, match="human_policy"):
        CrowdNav(human_policy="sfm")


def test_step_starts_a_new_episode_where_one_ends_and_vmaps():
    state = _state(humans=[(0.3, 0.0)])
    _, after, _, done, _ = jax.jit(ENV.step)(jax.random.key(1), state, jnp.zeros(2), PARAMS)
    assert bool(done) and int(after.steps) == 0 and float(after.time) == 0.0
    keys = jax.random.split(jax.random.key(2), 8)
    obs, states = jax.jit(jax.vmap(ENV.reset, in_axes=(0, None)))(keys, PARAMS)
    obs, states, reward, done, _ = jax.jit(jax.vmap(ENV.step, in_axes=(0, 0, 0, None)))(
        keys, states, jnp.zeros((8, 2)), PARAMS)
    assert obs.spatial_edges.shape == (8, ENV.num_humans, 12) and reward.shape == (8,)


def test_gst_predicts_the_humans_seen_at_both_of_the_last_two_steps():
    run = load_model("pretrained:crowdnav_sj_rand")
    env, params = CrowdNav.with_predictor(run, num_humans=4)
    state = _state(humans=[(1.0, 1.0), (2.0, -1.0)])
    history = np.zeros((4, 5, 2), np.float32)
    detected = np.zeros((4, 5), np.float32)
    history[0] = np.stack([1.0 + 0.25 * np.arange(-4, 1), np.ones(5)], -1)   # walks +x at 1 m/s
    detected[0] = 1
    history[1, -1], detected[1, -1] = (2.0, -1.0), 1                        # just appeared
    state = state.replace(tracks=state.tracks.replace(positions=jnp.asarray(history),
                                                      detected=jnp.asarray(detected)))
    obs, _, futures, predicted = env._observation(jax.random.key(0), state, params)
    np.testing.assert_array_equal(predicted, [True, False, False, False])
    # The walker is predicted onwards along +x; the newcomer's row repeats where it stands.
    assert np.all(np.diff(np.asarray(futures[0, :, 0])) > 0.1)
    row = np.asarray(obs.spatial_edges)[np.argsort(np.linalg.norm(
        [[1.0, 1.0], [2.0, -1.0]], axis=-1))[1]]
    np.testing.assert_allclose(row, np.tile([2.0, -1.0], 6))
    # The same futures as CrowdNav++'s own predictor (its -999 inputs and masks).
    crowdnav_env = CrowdNav(4, StreamModel(run.model_config, convention="crowdnav"))
    theirs = crowdnav_env._observation(jax.random.key(0), state, params)[2]
    np.testing.assert_allclose(futures[0], theirs[0], atol=1e-4)


def test_constant_velocity_predictions_and_conformal_radii_around_them(step_env):
    env = CrowdNav(4, environment.CONSTANT_VELOCITY, regions=Regions("dtaci", 0.1))
    state = _state(humans=[(2.0, 0.0)]).replace(
        human_goal=jnp.array([[2.0, 30.0]] + [[FAR, FAR]] * 3), human_v_pref=jnp.ones(4))
    state = state.replace(tracks=env.reset(jax.random.key(0), PARAMS)[1].tracks)  # with regions
    step = jax.jit(env.step_env)
    for t in range(12):                      # the human walks up at 1 m/s, seen throughout
        obs, state, *_ = step(jax.random.key(t), state, jnp.zeros(2), PARAMS)
    now = np.asarray(state.human_position[0]) - np.asarray(state.robot_position)
    row = np.asarray(obs.spatial_edges[0]).reshape(6, 2)
    np.testing.assert_allclose(row[1:], now + np.outer(np.arange(1, 6), [0.0, 0.25]), atol=1e-3)
    radii = np.asarray(obs.radii[0])
    assert radii.shape == (5,) and np.all(np.isfinite(radii))
    # One step ahead the walker, at constant velocity by now, is predicted exactly: its
    # radius is 0 up to rounding. Further ahead the errors of its start from rest remain.
    assert 0 <= radii[0] < 1e-6 and np.all(radii[1:] > 0.1)


def _walk_at_the_robot(env: CrowdNav, steps: int = 40) -> float:
    """A human walking from 3 m left of the robot (at rest at the origin) to 3 m right of
    it, moved by `env.human_velocities` alone: its closest approach to the robot (m)."""
    state = _state(humans=[(-3.0, 0.02)]).replace(
        human_goal=jnp.asarray([[3.0, 0.02]] + [[FAR + 10 * i, FAR] for i in range(1, 4)]),
        human_v_pref=jnp.ones(4))
    closest, velocities = np.inf, jax.jit(env.human_velocities)
    for _ in range(steps):
        velocity = velocities(state, PARAMS)
        state = state.replace(human_position=state.human_position + velocity * PARAMS.step_s,
                              human_velocity=velocity)
        closest = min(closest, float(jnp.linalg.norm(state.human_position[0])))
    return closest


@pytest.mark.parametrize("policy", [environment.ORCA, environment.SOCIAL_FORCE])
def test_reactive_humans_see_the_robot_and_give_way_to_it(policy):
    """CrowdNav++'s robot.visible: a human heading through the robot walks through it when
    humans ignore the robot and keeps clear of it (radii 0.3 + 0.3) when they see it."""
    assert _walk_at_the_robot(CrowdNav(4, human_policy=policy)) < 0.1
    assert _walk_at_the_robot(CrowdNav(4, human_policy=policy, reactive=True)) > 0.6


def test_a_speed_shift_makes_every_human_faster_from_its_time_on():
    env = CrowdNav(4, shift=environment.SPEED_SHIFT)
    state = _state(humans=[(0.0, 30.0)]).replace(
        human_goal=jnp.asarray([[10.0, 30.0]] + [[FAR + 10 * i, FAR] for i in range(1, 4)]),
        human_v_pref=jnp.full(4, 1.2))
    before = env.human_velocities(state.replace(time=jnp.asarray(PARAMS.shift_at_s - 0.25)),
                                  PARAMS)
    after = env.human_velocities(state.replace(time=jnp.asarray(PARAMS.shift_at_s)), PARAMS)
    np.testing.assert_allclose(before[0], [1.0, 0.0], atol=1e-5)       # ORCA's 1 m/s
    np.testing.assert_allclose(after[0], [1.5, 0.0], atol=1e-5)        # x 1.5, under 1.8


def test_a_policy_shift_switches_orca_humans_to_social_force():
    env = CrowdNav(4, shift=environment.POLICY_SHIFT)
    state = _state(humans=[(-0.5, 0.0), (0.5, 0.0)]).replace(
        human_goal=jnp.asarray([[4.0, 0.0], [-4.0, 0.0], [FAR, 20.0], [FAR, 40.0]]),
        human_v_pref=jnp.ones(4))
    early, late = (state.replace(time=jnp.asarray(t)) for t in (0.0, PARAMS.shift_at_s))
    np.testing.assert_allclose(env.human_velocities(early, PARAMS),
                               CrowdNav(4).human_velocities(early, PARAMS))
    np.testing.assert_allclose(env.human_velocities(late, PARAMS),
                               environment.social_force_velocities(late, PARAMS))
    with pytest.raises(ValueError, match="shift"):
        CrowdNav(4, human_policy=environment.SOCIAL_FORCE, shift=environment.POLICY_SHIFT)


@pytest.mark.parametrize("reactive", [False, True])
def test_truth_predictions_are_the_positions_the_humans_then_take(reactive):
    """TRUTH: the humans' next 5 positions by the environment's own rules; exact while no
    goal changes, no one is replaced and the robot keeps its velocity."""
    env = CrowdNav(6, environment.TRUTH, reactive=reactive)
    params = PARAMS.replace(goal_change_chance=0.0)
    _, state = env.reset(jax.random.key(3), params)
    step, truth = jax.jit(env.step_env), jax.jit(env._truth)
    positions, futures = [], []
    for t in range(12):
        _, state, _, _, _ = step(jax.random.key(t), state, jnp.array([0.3, 0.1]), params)
        positions.append(np.asarray(state.human_position))
        futures.append(np.asarray(truth(state, params)))
    for t in range(6):
        for k in range(5):
            np.testing.assert_allclose(futures[t][:, k], positions[t + k + 1], atol=1e-5)


def test_standing_predictions_hold_each_human_where_it_stands_and_get_discs():
    """STANDING (a planner without a predictor): every predicted step is where the human
    stands now; DtACI's discs are still calibrated around them."""
    env = CrowdNav(4, environment.STANDING, regions=Regions("dtaci", 0.1))
    _, state = env.reset(jax.random.key(0), PARAMS)
    for t in range(4):
        _, state, _, _, _ = env.step_env(jax.random.key(t), state, jnp.zeros(2), PARAMS)
    obs, _, futures, predicted = env._observation(jax.random.key(9), state, PARAMS)
    assert np.asarray(predicted).any()
    np.testing.assert_array_equal(futures, jnp.broadcast_to(state.human_position[:, None],
                                                            futures.shape))
    assert float(obs.radii.max()) > 0
    with pytest.raises(ValueError, match="model"):
        CrowdNav(4, "oracle")
