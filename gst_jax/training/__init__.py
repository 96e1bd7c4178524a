"""Training: state and schedule, the training step, ONE epoch loop, vmapped sweeps.

    state.py        TrainState, HParams, the optimiser, the release's schedule, key derivation
    step.py         the training loss and `make_train_step`
    loop.py         the epoch loop shared by single runs and sweeps, and `fit` (one run)
    persistence.py  the loop's checkpoints and metrics lines, and resuming from them
    selection.py    a fine-tuning's epoch, chosen on validation, and its report
    members.py      sweep members, stacking and their configs
    sweep.py        `fit_sweep` (one vmapped program) and its summaries

Nothing is re-exported here, so that importing one module does not import the loop (which
writes work directories through `gst_jax.runs`).
"""
