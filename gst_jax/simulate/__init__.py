"""Closed-loop multi-agent simulation driven by a trajectory predictor (the paper's Fig. 5).

    scenarios.py  the four robot/human scenarios as initial states
    loop.py       the jitted closed loop and the step models (constant velocity, GST)
    measures.py   the robot's safety and efficiency, freezing and U-turn detection
    figures.py    a run as a PNG and an animated GIF
    study.py      every model on every scenario, with results.json

`python -m gst_jax.simulate` is the command (`gst_jax/simulate/__main__.py`).
"""

from gst_jax.simulate.loop import StepModel, constant_velocity_model, gst_model, simulate
from gst_jax.simulate.measures import (ROBOT_COLLISION_DISTANCE, freezing_or_u_turn,
                                       robot_measures)
from gst_jax.simulate.scenarios import (SCENARIOS, Scenario, boundary_wanderers, intersection,
                                        late_crossing, oncoming_group)

__all__ = ["ROBOT_COLLISION_DISTANCE", "SCENARIOS", "Scenario", "StepModel",
           "boundary_wanderers", "constant_velocity_model", "freezing_or_u_turn", "gst_model",
           "intersection", "late_crossing", "oncoming_group", "robot_measures", "simulate",
           # The modules of CrowdNav++'s task, pages of their own in the API reference.
           "environment", "navigation", "planner"]
