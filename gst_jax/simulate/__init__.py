"""Closed-loop simulation of people and a robot: the paper's encounters and CrowdNav++'s task,
moving their agents by one core.

    agents/     how agents move (the core both use): ORCA, social force, a holonomic body,
                a trajectory predictor's first step
    paper/      the paper's Fig. 5: scenarios, the jitted closed loop, random encounters,
                measures, figures, the study (`python -m gst_jax.simulate`)
    crowdnav/   CrowdNav++'s navigation task: the jittable environment, the sampling MPC
                planner, episodes and their measures (`python -m gst_jax.navigate`)
    crowds.py   synthetic crowds written as training data (numpy)

Here: the paper's loop, its scenarios and measures.
"""

from gst_jax.simulate.agents.predicted import StepModel, constant_velocity_model, gst_model
from gst_jax.simulate.paper.loop import MODEL_HUMANS, ORCA_HUMANS, simulate
from gst_jax.simulate.paper.measures import (
                                             ROBOT_COLLISION_DISTANCE,
                                             freezing_or_u_turn,
                                             robot_measures,
)
from gst_jax.simulate.paper.scenarios import (
                                             SCENARIOS,
                                             Scenario,
                                             boundary_wanderers,
                                             intersection,
                                             late_crossing,
                                             oncoming_group,
)

__all__ = ["MODEL_HUMANS", "ORCA_HUMANS", "ROBOT_COLLISION_DISTANCE", "SCENARIOS", "Scenario",
           "StepModel", "boundary_wanderers", "constant_velocity_model", "freezing_or_u_turn",
           "gst_model", "intersection", "late_crossing", "oncoming_group", "robot_measures",
           "simulate",
           # The folders, pages of their own in the API reference.
           "agents", "paper", "crowdnav"]
