"""How agents move, the core of both simulators (`paper/`, `crowdnav/`).

    orca.py       ORCA inside jit (RVO2's algorithm): every agent's new velocity
    motion.py     a holonomic body, the velocity towards a goal, CrowdNav++'s social force
    predicted.py  agents moved by a trajectory predictor's first step (constant velocity, GST)
"""

from gst_jax.simulate.agents.motion import (
                                            SocialForce,
                                            holonomic,
                                            social_force_velocities,
                                            toward_goal,
)
from gst_jax.simulate.agents.orca import OrcaParams, orca_velocities
from gst_jax.simulate.agents.predicted import StepModel, constant_velocity_model, gst_model

__all__ = ["OrcaParams", "SocialForce", "StepModel", "constant_velocity_model", "gst_model",
           "holonomic", "orca_velocities", "social_force_velocities", "toward_goal"]
