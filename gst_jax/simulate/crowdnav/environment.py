"""CrowdNav++'s navigation task as a pure, jittable environment, GST in the loop.

gymnax's convention: `env.reset(key, params) -> (obs, state)` and
`env.step(key, state, action, params) -> (obs, state, reward, done, info)`, both pure, so a
jitted `jax.vmap` steps thousands of episodes at once and an RL trainer in JAX (rejax,
purejaxrl) takes the environment as it is. `step` starts a new episode where one ends.

The task is CrowdNav++'s default (Shuijing725/CrowdNav_Prediction_AttnGraph, commit 3907731:
`crowd_nav/configs/config.py`, `crowd_sim/envs/crowd_sim_var_num.py`,
`crowd_sim_pred_real_gst.py`, `rl/vec_env/vec_pretext_normalize.py`):

- 0.25 s steps, 50 s episodes (timeout once 49 s have passed, before collision or arrival);
- a holonomic robot (radius 0.3, speed up to 1 m/s; the action is its velocity, scaled down
  to that speed) from a start to a goal in [-6, 6]^2 at least 8 m apart;
- 20 humans (radius U(0.3, 0.5), preferred speed U(0.5, 1.5)) who start on a circle of
  radius 6 sqrt 2 (shifted by U(0, 2) m per axis) and walk to the opposite point with ORCA
  (`agents/orca.py`; time horizon 5 s, all 19 others, neighbour distance U(5, 10) per episode,
  radius + 0.16 m) or, CrowdNav++'s option `humans.policy = "social_force"`, with its social
  force (`human_policy=SOCIAL_FORCE`), not seeing the robot (with `reactive`, CrowdNav++'s
  `robot.visible = True`, they see it as one more agent, radius 0.3 + 0.16 m, and give way to
  it); every 5 s each changes goal with probability 0.5, and one that reaches its goal is
  replaced by a new human;
- the robot detects a human whose surface lies within 5 m (field of view 360 degrees);
- reward, on the state before the step's move (CrowdNav++'s order): timeout 0, collision
  (centres closer than the radii) -20 and done, arrival (within 0.3 m of the goal) +10 and
  done, discomfort (surface distance d < 0.25 m) 2.5 (d - 0.25), else 2 x the progress
  towards the goal since the last step without discomfort; then, on the new state, the
  prediction penalty: the worst of -20 / 2^(k+1) over predicted steps k = 1..5 of humans
  predicted now that come within 0.6 m of the robot;
- the observation: the robot's [px, py, radius, gx, gy, v_pref, theta], its velocity, and per
  human its position now and at each predicted step relative to the robot, sorted nearest
  first, 15 for a human not detected; the detection mask in id order and the number
  detected (at least 1).

Predictions come from `gst_jax.stream_core.predict_slots` over each human's last obs_len detected
positions (CrowdNav++'s 5), repeat each human's last displacement (CONSTANT_VELOCITY), hold
each human where it stands (STANDING: a planner without a predictor) or are the simulator's
own next positions (TRUTH: every human moved on by the rules above, its goal kept, the robot
at its velocity; exact but for goal changes and replaced humans, an upper bound on what any
predictor can give), for the humans detected at both of the last two steps; without a model
the observation carries the current positions only (CrowdNav++'s no-prediction task). With
`regions`, each predicted step also gets a conformal radius (`gst_jax.conformal.Regions`),
scored as the humans move on.

A distribution shift (`shift`), from `EnvParams.shift_at_s` into every episode: SPEED_SHIFT
makes every human faster by `speed_factor` (preferred and top speed), POLICY_SHIFT switches
ORCA humans to social force (GenSafeNav's shift between calibration and test; online regions
calibrate on the episode's first part).

Where this differs from CrowdNav++, on purpose: rejection sampling of starts and goals takes
the first acceptable of a fixed number of draws (CrowdNav++ draws until one is); a new
episode starts with empty histories (CrowdNav++ keeps the last episode's in its predictor's
buffer); the prediction penalty of an episode's last step is computed on that episode
(CrowdNav++ computes it on the next episode's first observation); each human's ORCA sees
every other human's current radius (CrowdNav++'s reused simulators keep a replaced human's
old one).

One job, though over 400 lines: CrowdNav++'s task, its rules (spawning, goals, detection,
reward) beside the environment that applies them in CrowdNav++'s order, so that they read
against CrowdNav++'s `crowd_sim` files together.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import flax
import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from gst_jax import conformal
from gst_jax.adaptation import Adaptation
from gst_jax.conformal import Regions
from gst_jax.errors import RunError
from gst_jax.model import Params
from gst_jax.predictors import GST, ConstantVelocity, Predictor, Standing, Truth
from gst_jax.simulate.agents import motion
from gst_jax.simulate.agents.orca import OrcaParams, orca_velocities
from gst_jax.stream_core import StreamState, adapt, init_state, update_regions

# Outcomes of a step (info["outcome"]), CrowdNav++'s info classes.
NOTHING, REACH_GOAL, COLLISION, TIMEOUT, DISCOMFORT = range(5)
OUTCOMES = ("nothing", "reach_goal", "collision", "timeout", "discomfort")
# A row of a human not detected, CrowdNav++'s filler.
UNDETECTED = 15.0
# Draws per rejection sample: of a human's start or goal (nearly always the first is clear),
# and of the robot's start and goal (about 3 in 10 pairs are 8 m apart: all 32 fail once in
# 10^5 episodes, and then the last is taken).
TRIES = 8
ROBOT_TRIES = 32
# `CrowdNav.model` for predictions that repeat each human's last displacement, that hold each
# human where it stands, and that are the simulator's own next positions.
CONSTANT_VELOCITY, STANDING, TRUTH = ConstantVelocity(), Standing(), Truth()
# `CrowdNav.human_policy`: how the humans walk (CrowdNav++'s `humans.policy`).
ORCA, SOCIAL_FORCE = "orca", "social_force"
# `CrowdNav.shift`: none, the humans speed up, or ORCA humans switch to social force.
NO_SHIFT, SPEED_SHIFT, POLICY_SHIFT = "none", "speed", "policy"


class EnvParams(flax.struct.PyTreeNode):
    """The task's numbers (CrowdNav++'s defaults) and the predictor's weights (None: no
    prediction). Every field may be traced, vmapped or changed between calls."""

    predictor: Params | None = None
    step_s: float = 0.25
    time_limit_s: float = 50.0
    arena_size: float = 6.0
    min_start_goal: float = 8.0
    circle_radius: float = 6.0 * math.sqrt(2.0)
    robot_radius: float = 0.3
    robot_v_pref: float = 1.0
    human_radius: tuple[float, float] = (0.3, 0.5)
    human_v_pref: tuple[float, float] = (0.5, 1.5)
    sensor_range: float = 5.0
    fov: float = 2.0 * math.pi
    discomfort_dist: float = 0.25
    discomfort_factor: float = 10.0
    success_reward: float = 10.0
    collision_penalty: float = -20.0
    potential_factor: float = 2.0
    goal_change_every_s: float = 5.0
    goal_change_chance: float = 0.5
    safety_space: float = 0.15
    time_horizon: float = 5.0
    neighbour_dist: tuple[float, float] = (5.0, 10.0)
    # Social force (CrowdNav++'s `sf`): strength A, range B (m), inverse relocation time KI.
    force_strength: float = 2.0
    force_range: float = 1.0
    relocation_rate: float = 1.0
    prediction_radius: float = 0.6
    # A shift (CrowdNav.shift) takes effect this far into every episode: about half of a
    # successful episode's 12-15 s.
    shift_at_s: float = 6.0
    speed_factor: float = 1.5


class EnvState(flax.struct.PyTreeNode):
    """One episode (H humans, T = obs_len observed steps). Positions in metres, world frame.

    robot_position, robot_velocity, robot_goal: (2,); humans' position, velocity, goal: (H, 2);
    human_radius, human_v_pref: (H,); neighbour_dist: () ORCA's, this episode's;
    potential: () minus the goal distance at the last step without discomfort; time: ()
    seconds; steps: () int32; tracks: what the robot has seen of each human, slot i human i
    (`StreamState`: the last T positions and detections, and with regions the predictions
    being scored and the conformal state).
    """

    robot_position: jax.Array
    robot_velocity: jax.Array
    robot_goal: jax.Array
    human_position: jax.Array
    human_velocity: jax.Array
    human_goal: jax.Array
    human_radius: jax.Array
    human_v_pref: jax.Array
    neighbour_dist: jax.Array
    potential: jax.Array
    time: jax.Array
    steps: jax.Array
    tracks: StreamState


class Observation(NamedTuple):
    """What the robot's policy sees (CrowdNav++'s keys): robot_node (7,) [px, py, radius,
    gx, gy, v_pref, theta]; temporal_edges (2,) its velocity; spatial_edges (H, 2 (P + 1))
    each human's position now, then at its P predicted steps, relative to the robot, nearest
    first (15 where not detected); visible_masks (H,) in id order; detected_human_num ();
    radii (H, P) the conformal radius around each predicted step, rows as spatial_edges' (0
    without regions or prediction)."""

    robot_node: jax.Array
    temporal_edges: jax.Array
    spatial_edges: jax.Array
    visible_masks: jax.Array
    detected_human_num: jax.Array
    radii: jax.Array


@dataclasses.dataclass(frozen=True)
class CrowdNav:
    """The environment: `num_humans` humans; predictions over `obs_len` observed steps for
    `pred_len` by `model`: a `gst_jax.predictors.Predictor` (a model's `GST`, its weights in
    `EnvParams.predictor`; CONSTANT_VELOCITY, STANDING, TRUTH) or None (no prediction); with
    `adaptation`, the predictions corrected online from their delayed scores
    (`gst_jax.adaptation`); with `regions`, conformal radii around the predicted steps
    (`gst_jax.conformal.Regions`); the humans walk by ORCA or SOCIAL_FORCE (`human_policy`),
    seeing the robot where `reactive`, shifted by `shift`. A replaced human takes its
    predecessor's slot and, as in CrowdNav++, its history; with `fresh_tracks` its history
    starts empty, as a tracker's new identity would."""

    num_humans: int = 20
    model: Predictor | None = None
    obs_len: int = 5
    pred_len: int = 5
    regions: Regions | None = None
    human_policy: str = ORCA
    reactive: bool = False
    shift: str = NO_SHIFT
    adaptation: Adaptation | None = None
    fresh_tracks: bool = False

    def __post_init__(self):
        if self.human_policy not in (ORCA, SOCIAL_FORCE):
            raise ValueError(f"human_policy must be {ORCA!r} or {SOCIAL_FORCE!r}, "
                             f"got {self.human_policy!r}")
        if self.shift not in (NO_SHIFT, SPEED_SHIFT, POLICY_SHIFT):
            raise ValueError(f"shift must be one of {NO_SHIFT!r}, {SPEED_SHIFT!r}, "
                             f"{POLICY_SHIFT!r}, got {self.shift!r}")
        if self.shift == POLICY_SHIFT and self.human_policy != ORCA:
            raise ValueError("shift 'policy' switches ORCA humans to social force: "
                             f"human_policy must be {ORCA!r}")
        if self.model is not None and not hasattr(self.model, "predict"):
            raise ValueError(f"model must be a gst_jax.predictors.Predictor (GST, "
                             f"ConstantVelocity, Standing, Truth) or None, got {self.model!r}")

    @classmethod
    def with_predictor(cls, predictor, num_humans: int = 20, regions: Regions | None = None,
                       human_policy: str = ORCA, reactive: bool = False, shift: str = NO_SHIFT,
                       adaptation: Adaptation | None = None, fresh_tracks: bool = False
                       ) -> tuple["CrowdNav", EnvParams]:
        """The environment and its params, predictions by `predictor`: a loaded model
        (`gst_jax.runs.load_model`; mean mode, as CrowdNav++'s predictor) whose time step is
        the environment's (RunError otherwise), another `Predictor` (CONSTANT_VELOCITY,
        STANDING, TRUTH) or None."""
        humans: dict[str, Any] = dict(human_policy=human_policy, reactive=reactive, shift=shift,
                                      adaptation=adaptation, fresh_tracks=fresh_tracks)
        if predictor is None or hasattr(predictor, "predict"):
            return cls(num_humans, predictor, regions=regions, **humans), EnvParams()
        run, config, params = predictor, predictor.model_config, EnvParams()
        if not math.isclose(config.step_s, params.step_s):
            raise RunError(f"{run.name} predicts steps of {config.step_s:g} s, the environment "
                           f"moves in steps of {params.step_s:g} s (CrowdNav++'s task): its "
                           f"predictions would be read at the wrong times; use a model of "
                           f"{params.step_s:g} s steps, e.g. pretrained:crowdnav_sj_rand")
        return (cls(num_humans, GST(config), config.obs_len, config.pred_len, regions,
                    **humans), params.replace(predictor=run.params))

    @property
    def default_params(self) -> EnvParams:
        return EnvParams()

    # -- gymnax's interface -------------------------------------------------------------
    def reset(self, key: jax.Array, params: EnvParams) -> tuple[Observation, EnvState]:
        """A new episode: its first observation and state."""
        robot_key, humans_key, orca_key, predict_key = jax.random.split(key, 4)
        start, goal = _robot_start_and_goal(robot_key, params)
        far = jnp.full((self.num_humans, 2), 1e6)
        zero = jnp.zeros(self.num_humans)
        state = EnvState(
            robot_position=start, robot_velocity=jnp.zeros(2), robot_goal=goal,
            human_position=far, human_velocity=jnp.zeros((self.num_humans, 2)), human_goal=far,
            human_radius=zero, human_v_pref=zero,
            neighbour_dist=_uniform(orca_key, (), params.neighbour_dist),
            potential=-jnp.linalg.norm(start - goal), time=jnp.zeros(()),
            steps=jnp.zeros((), jnp.int32),
            tracks=init_state(self.num_humans, self.obs_len, self.regions, self.pred_len,
                              self.adaptation
                              ).replace(track_ids=jnp.arange(self.num_humans, dtype=jnp.int32)))
        # Humans are placed one after another, each clear of those before it.
        state = _respawn(humans_key, state, params, jnp.ones(self.num_humans, bool))
        state = _observed(state, params)
        obs, state, _, _ = self._observation(predict_key, state, params, fresh=True)
        return obs, state

    def step(self, key: jax.Array, state: EnvState, action: jax.Array, params: EnvParams
             ) -> tuple[Observation, EnvState, jax.Array, jax.Array, dict]:
        """One step of 0.25 s under `action` (the robot's velocity, (2,) m/s); a new episode
        where this one ends (gymnax's auto-reset: obs and state are the new episode's)."""
        step_key, reset_key = jax.random.split(key)
        obs, state, reward, done, info = self.step_env(step_key, state, action, params)
        new_obs, new_state = self.reset(reset_key, params)
        pick = lambda new, old: jnp.where(done, new, old)
        return (jax.tree.map(pick, new_obs, obs), jax.tree.map(pick, new_state, state),
                reward, done, info)

    def step_env(self, key: jax.Array, state: EnvState, action: jax.Array, params: EnvParams
                 ) -> tuple[Observation, EnvState, jax.Array, jax.Array, dict]:
        """One step without the reset: reward and outcome on the state before the move
        (CrowdNav++'s order), then the move, the observation, and the humans' new goals."""
        predict_key, goals_key, respawn_key = jax.random.split(key, 3)
        robot_position, action = motion.holonomic(state.robot_position, action,
                                                  params.robot_v_pref, params.step_s)
        human_velocity = self.human_velocities(state, params)
        reward, done, info, potential = _reward(state, params)

        state = state.replace(
            robot_position=robot_position, robot_velocity=action,
            human_position=state.human_position + human_velocity * params.step_s,
            human_velocity=human_velocity, potential=potential,
            time=state.time + params.step_s, steps=state.steps + 1)
        state = _observed(state, params)
        obs, state, futures, predicted = self._observation(predict_key, state, params)
        reward = reward + _prediction_penalty(state, futures, predicted, params)
        state = _new_goals(goals_key, state, params)
        arrived = jnp.linalg.norm(state.human_goal - state.human_position, axis=-1) < (
            state.human_radius)
        state = _respawn(respawn_key, state, params, arrived)
        if self.fresh_tracks:
            state = state.replace(tracks=state.tracks.replace(detected=jnp.where(
                arrived[:, None], 0.0, state.tracks.detected)))
        if self.regions is not None:      # a new person's predictions start afresh
            assert state.tracks.feed is not None, "tracks made with the regions have a feed"
            state = state.replace(tracks=state.tracks.replace(
                feed=conformal.reset_slots(state.tracks.feed, arrived)))
        if self.adaptation is not None:
            assert state.tracks.adaptation is not None, "tracks made with the adaptation"
            state = state.replace(tracks=state.tracks.replace(
                adaptation=self.adaptation.reset_slots(state.tracks.adaptation, arrived)))
        return obs, state, reward, done, {**info, "replaced": arrived}

    # -- parts ----------------------------------------------------------------------------
    def human_velocities(self, state: EnvState, params: EnvParams) -> jax.Array:
        """Every human's new velocity (H, 2) among the other humans (and the robot, where
        `reactive`). ORCA: towards its goal at 1 m/s (less within 1 m of it), at most its
        preferred speed; both `speed_factor` times more once a speed shift has begun."""
        shifted = state.time >= params.shift_at_s
        factor: float | jax.Array = 1.0
        if self.shift == SPEED_SHIFT:
            factor = jnp.where(shifted, params.speed_factor, 1.0)
            state = state.replace(human_v_pref=state.human_v_pref * factor)
        if self.human_policy == SOCIAL_FORCE:
            return social_force_velocities(state, params, self.reactive)
        orca = self._orca_velocities(state, params, factor)
        if self.shift == POLICY_SHIFT:
            return jnp.where(shifted, social_force_velocities(state, params, self.reactive),
                             orca)
        return orca

    def _orca_velocities(self, state: EnvState, params: EnvParams, factor) -> jax.Array:
        preferred = motion.toward_goal(state.human_position, state.human_goal, factor)
        agents: tuple[jax.Array, ...] = (
            state.human_position, state.human_velocity,
            state.human_radius + 0.01 + params.safety_space, state.human_v_pref, preferred)
        if self.reactive:         # the robot is one more agent, as CrowdNav++ adds it
            robot: tuple[ArrayLike, ...] = (
                state.robot_position, state.robot_velocity,
                params.robot_radius + 0.01 + params.safety_space, params.robot_v_pref,
                state.robot_velocity)
            agents = tuple(jnp.concatenate([h, jnp.reshape(r, (1, *h.shape[1:]))])
                           for h, r in zip(agents, robot))
        count = agents[0].shape[0]
        orca = OrcaParams(params.time_horizon, count - 1, state.neighbour_dist)
        position, velocity, radius, max_speed, wanted = agents
        return orca_velocities(position, velocity, radius, max_speed, wanted,
                               jnp.ones(count, bool), orca, params.step_s)[:self.num_humans]

    def _truth(self, state: EnvState, params: EnvParams) -> jax.Array:
        """The humans' next `pred_len` positions (H, P, 2) by the environment's own rules:
        goals kept, no one replaced, the robot at its velocity."""
        def move(state, _):
            velocity = self.human_velocities(state, params)
            state = state.replace(
                human_position=state.human_position + velocity * params.step_s,
                human_velocity=velocity, time=state.time + params.step_s,
                robot_position=state.robot_position + state.robot_velocity * params.step_s)
            return state, state.human_position

        _, futures = jax.lax.scan(move, state, length=self.pred_len)
        return jnp.swapaxes(futures, 0, 1)

    def _observation(self, key: jax.Array, state: EnvState, params: EnvParams,
                     fresh: bool = False) -> tuple[Observation, EnvState, jax.Array, jax.Array]:
        """The observation, the state with the regions updated, the predicted positions
        (H, P, 2) (where a human stands, for those not predicted) and which humans have them
        (H,): those detected at both of the last two steps. On an episode's first
        observation (`fresh`) that is none, and the predictor is not called: gymnax's
        auto-reset builds such an observation at every step."""
        tracks = state.tracks
        visible = tracks.detected[:, -1] > 0
        predicted = (tracks.detected[:, -2:] > 0).all(axis=-1)
        now = state.human_position
        predict_key = None
        if self.model is not None and self.model.uses_key:
            predict_key, key = jax.random.split(key)
        if self.model is None or fresh:
            futures = jnp.broadcast_to(now[:, None], (self.num_humans, self.pred_len, 2))
            predicted = jnp.zeros_like(predicted)
        else:
            slots, _ = self.model.predict(params.predictor, predict_key, tracks.positions,
                                          tracks.detected, truth=lambda: self._truth(state,
                                                                                      params))
            if self.adaptation is not None:
                tracks, slots = adapt(self.adaptation, tracks, slots, predicted)
                state = state.replace(tracks=tracks)
            futures = jnp.swapaxes(slots[0], 0, 1)                              # (H, P, 2)
        futures = jnp.where(predicted[:, None, None], futures, now[:, None])
        radii = jnp.zeros((self.num_humans, self.pred_len))
        if self.regions is not None and self.model is not None:
            tracks, radii, _ = update_regions(
                self.regions, tracks, key, jnp.zeros(self.num_humans, bool),
                jnp.swapaxes(futures, 0, 1)[None], predicted)
            state = state.replace(tracks=tracks)
        relative = jnp.concatenate([now[:, None], futures], axis=1) - state.robot_position
        relative = jnp.where(visible[:, None, None], relative, UNDETECTED)
        order = jnp.argsort(jnp.linalg.norm(relative[:, 0], axis=-1), stable=True)
        robot_node = jnp.concatenate([state.robot_position, jnp.array([params.robot_radius]),
                                      state.robot_goal, jnp.array([params.robot_v_pref,
                                                                   math.pi / 2])])
        obs = Observation(robot_node=robot_node, temporal_edges=state.robot_velocity,
                          spatial_edges=relative[order].reshape(self.num_humans, -1),
                          visible_masks=visible,
                          detected_human_num=jnp.maximum(visible.sum(), 1).astype(jnp.float32),
                          radii=radii[order])
        return obs, state, futures, predicted


def social_force_velocities(state: EnvState, params: EnvParams, reactive: bool = False
                            ) -> jax.Array:
    """Every human's social-force velocity (H, 2) (`agents.motion`), the robot among those
    who push where `reactive`."""
    others, others_radius = state.human_position, state.human_radius
    if reactive:
        others = jnp.concatenate([others, state.robot_position[None]])
        others_radius = jnp.concatenate([others_radius, jnp.array([params.robot_radius])])
    force = motion.SocialForce(params.force_strength, params.force_range,
                               params.relocation_rate)
    return motion.social_force_velocities(
        state.human_position, state.human_velocity, state.human_goal, state.human_radius,
        state.human_v_pref, others, others_radius, force, params.step_s)


def _uniform(key, shape, bounds):
    return jax.random.uniform(key, shape, minval=bounds[0], maxval=bounds[1])


def _first_true(accepted: jax.Array) -> jax.Array:
    """The index of the first True of (tries,), the last if none is."""
    return jnp.where(accepted.any(), jnp.argmax(accepted), accepted.shape[0] - 1)


def _robot_start_and_goal(key: jax.Array, params: EnvParams) -> tuple[jax.Array, jax.Array]:
    """Start and goal uniform in the arena's square, at least min_start_goal apart."""
    draws = jax.random.uniform(key, (ROBOT_TRIES, 2, 2), minval=-params.arena_size,
                               maxval=params.arena_size)
    accepted = jnp.linalg.norm(draws[:, 0] - draws[:, 1], axis=-1) >= params.min_start_goal
    start, goal = draws[_first_true(accepted)]
    return start, goal


def _clear(candidates: jax.Array, radius: jax.Array, state: EnvState, params: EnvParams,
           others: jax.Array) -> jax.Array:
    """Which candidate points (tries, 2) keep radius + theirs + discomfort_dist away from the
    robot's position and goal and from the positions and goals of the humans `others` (H,)."""
    centres = jnp.concatenate([state.robot_position[None], state.robot_goal[None],
                               state.human_position, state.human_goal])
    radii = jnp.concatenate([jnp.full(2, params.robot_radius), state.human_radius,
                             state.human_radius])
    counted = jnp.concatenate([jnp.ones(2, bool), others, others])
    distance = jnp.linalg.norm(candidates[:, None] - centres[None], axis=-1)
    return jnp.all((distance >= radius + radii + params.discomfort_dist) | ~counted, axis=-1)


def _on_circle(key: jax.Array, shape: tuple[int, ...], params: EnvParams) -> jax.Array:
    """(*shape, 2) points of the circle of radius circle_radius, uniform in angle."""
    angle = jax.random.uniform(key, shape, maxval=2 * math.pi)
    return params.circle_radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)


def _respawn(key: jax.Array, state: EnvState, params: EnvParams, which: jax.Array) -> EnvState:
    """Humans `which` (H,) replaced by new ones, one after another: a new radius and speed,
    a start on the circle (shifted by U(0, 2) per axis) clear of everyone else, and the
    opposite point as goal. The draws are made at once, the choices in turn."""
    count = which.shape[0]
    radius_key, speed_key, angle_key, shift_key = jax.random.split(key, 4)
    radii = _uniform(radius_key, (count,), params.human_radius)
    speeds = _uniform(speed_key, (count,), params.human_v_pref)
    starts = _on_circle(angle_key, (count, TRIES), params) + 2.0 * jax.random.uniform(
        shift_key, (count, TRIES, 2))

    def one(state, inputs):
        i, replace, radius, speed, start = inputs
        others = jnp.arange(count) != i
        start = start[_first_true(_clear(start, radius, state, params, others))]
        new = state.replace(
            human_position=state.human_position.at[i].set(start),
            human_velocity=state.human_velocity.at[i].set(0.0),
            human_goal=state.human_goal.at[i].set(-start),
            human_radius=state.human_radius.at[i].set(radius),
            human_v_pref=state.human_v_pref.at[i].set(speed))
        return jax.tree.map(lambda a, b: jnp.where(replace, a, b), new, state), None

    state, _ = jax.lax.scan(one, state, (jnp.arange(count), which, radii, speeds, starts))
    return state


def _new_goals(key: jax.Array, state: EnvState, params: EnvParams) -> EnvState:
    """Every goal_change_every_s seconds, each human with probability goal_change_chance
    takes a new goal, one after another: a point of the circle, shifted by (U - 0.5) v_pref
    per axis, clear of everyone else."""
    count = state.human_radius.shape[0]
    every = jnp.round(params.goal_change_every_s / params.step_s).astype(jnp.int32)
    chance_key, angle_key, shift_key = jax.random.split(key, 3)
    change = (state.steps % every == 0) & (
        jax.random.uniform(chance_key, (count,)) <= params.goal_change_chance)
    goals = _on_circle(angle_key, (count, TRIES), params) + (
        jax.random.uniform(shift_key, (count, TRIES, 2)) - 0.5) * state.human_v_pref[:, None, None]

    def one(state, inputs):
        i, change, goal = inputs
        others = jnp.arange(count) != i
        goal = goal[_first_true(_clear(goal, state.human_radius[i], state, params, others))]
        return state.replace(human_goal=state.human_goal.at[i].set(
            jnp.where(change, goal, state.human_goal[i]))), None

    state, _ = jax.lax.scan(one, state, (jnp.arange(count), change, goals))
    return state


def detected_humans(state: EnvState, params: EnvParams) -> jax.Array:
    """(H,) which humans the robot detects: surface distance within the sensor's range and,
    with a field of view under 360 degrees, the direction within half of it of the robot's
    heading (its velocity's; a robot at rest faces +x). A human at the robot's very centre
    is not detected (CrowdNav++'s undefined angle)."""
    offset = state.human_position - state.robot_position
    distance = jnp.linalg.norm(offset, axis=-1)
    in_range = distance - state.human_radius - params.robot_radius <= params.sensor_range
    heading = jnp.arctan2(state.robot_velocity[1], state.robot_velocity[0])
    bearing = jnp.arctan2(offset[:, 1], offset[:, 0]) - heading
    off_axis = jnp.abs(jnp.arctan2(jnp.sin(bearing), jnp.cos(bearing)))
    return in_range & (off_axis <= params.fov / 2) & (distance > 0)


def _observed(state: EnvState, params: EnvParams) -> EnvState:
    """The histories one step later, with the humans detected now."""
    seen = detected_humans(state, params)
    tracks = state.tracks
    positions = jnp.roll(tracks.positions, -1, axis=1).at[:, -1].set(
        jnp.where(seen[:, None], state.human_position, 0.0))
    detected = jnp.roll(tracks.detected, -1, axis=1).at[:, -1].set(seen.astype(jnp.float32))
    return state.replace(tracks=tracks.replace(positions=positions, detected=detected))


def _reward(state: EnvState, params: EnvParams) -> tuple[jax.Array, jax.Array, dict, jax.Array]:
    """CrowdNav++'s reward on a state: (reward, done, info, the potential after it)."""
    surface = (jnp.linalg.norm(state.human_position - state.robot_position, axis=-1)
               - state.human_radius - params.robot_radius)
    closest = surface.min()
    collision = closest < 0
    to_goal = jnp.linalg.norm(state.robot_position - state.robot_goal)
    arrived = to_goal < params.robot_radius
    discomfort = closest < params.discomfort_dist
    timeout = state.time >= params.time_limit_s - 1
    outcome = jnp.select([timeout, collision, arrived, discomfort],
                         [TIMEOUT, COLLISION, REACH_GOAL, DISCOMFORT], NOTHING)
    reward = jnp.select(
        [timeout, collision, arrived, discomfort],
        [0.0, params.collision_penalty, params.success_reward,
         (closest - params.discomfort_dist) * params.discomfort_factor * params.step_s],
        params.potential_factor * (-to_goal - state.potential))
    potential = jnp.where(outcome == NOTHING, -to_goal, state.potential)
    done = timeout | collision | arrived
    return reward, done, {"outcome": outcome, "min_distance": closest}, potential


def _prediction_penalty(state: EnvState, futures: jax.Array, predicted: jax.Array,
                        params: EnvParams) -> jax.Array:
    """The worst of collision_penalty / 2^(k+1) over the predicted steps k = 1..P of the
    humans predicted now (H,) whose futures (H, P, 2) come within prediction_radius of the
    robot; 0 without."""
    near = jnp.linalg.norm(futures - state.robot_position, axis=-1) < params.prediction_radius
    steps = jnp.arange(1, futures.shape[1] + 1)
    penalty = params.collision_penalty / 2.0 ** (steps + 1)                      # (P,)
    return jnp.min(jnp.where(near & predicted[:, None], penalty, 0.0))
