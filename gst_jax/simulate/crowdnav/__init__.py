"""CrowdNav++'s navigation task (Shuijing725/CrowdNav_Prediction_AttnGraph), GST in the loop.

    environment.py  the task as a pure, jittable gymnax-style environment
    planner.py      a sampling MPC over predicted positions and conformal discs
    navigation.py   episodes in one program, CrowdNav++'s measures, records
    figures.py      an episode as an animated GIF
"""
