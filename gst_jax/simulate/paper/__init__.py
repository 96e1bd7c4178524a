"""The paper's closed-loop study (Fig. 5): a robot moved by the model's own prediction among
people.

    scenarios.py   the four robot/human scenarios as initial states
    loop.py        the jitted closed loop (people moved by the model, or by ORCA)
    encounters.py  thousands of random encounters in one vmapped program
    measures.py    the robot's safety and efficiency, freezing and U-turn detection
    figures.py     a run as a PNG and an animated GIF, encounter rates
    study.py       every model on every scenario, with results.json
"""
