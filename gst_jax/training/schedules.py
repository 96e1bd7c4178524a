"""The learning-rate and temperature schedules, chosen by name (`TrainConfig.schedule`).

Both are optax schedules of the epoch, constant within it (docs/MODEL.md 3): the learning
rate of epochs done before it, the Gumbel temperature of epochs done at its end (the release
anneals from its first epoch's end, so the last epoch trains at tau_end).

    paper       Adam 1e-3 x 0.3 every 50 epochs, tau 0.5 -> 0.03 linearly over the run
    compressed  the same shape fitted to the run's length E: x 0.3 every E/4 epochs, so that
                `--epochs 200` gives exactly the paper schedule
    finetune    the learning rate constant and tau held at tau_end: a trained model was
                annealed to tau_end, and starting it again at 0.5 with Adam at 1e-3 (the paper
                schedule) undoes what it learnt before it learns anything new
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import optax

from gst_jax.config import TrainConfig


@dataclasses.dataclass(frozen=True)
class Schedule:
    """What a training's schedule sets per epoch (see the module docstring)."""

    learning_rate: optax.Schedule
    temperature: optax.Schedule

    def at(self, epoch: int) -> tuple[float, float]:
        """(learning rate, tau) of a 1-based epoch.

        Evaluated in float64, then rounded once: the values the paper schedule had when it was
        Python arithmetic, so runs trained before (Table I) resume bit for bit."""
        with jax.enable_x64(True):
            return (float(np.float32(self.learning_rate(epoch - 1))),
                    float(np.float32(self.temperature(epoch))))


def _decay_every(train_config: TrainConfig) -> float:
    if train_config.schedule == "paper":
        return train_config.lr_decay_every
    return train_config.epochs / 4


def make_schedule(train_config: TrainConfig) -> Schedule:
    """The schedule `train_config.schedule` names, over `train_config.epochs`."""
    if train_config.schedule == "finetune":
        return Schedule(learning_rate=optax.constant_schedule(train_config.learning_rate),
                        temperature=optax.constant_schedule(train_config.tau_end))
    return Schedule(
        learning_rate=optax.exponential_decay(
            train_config.learning_rate, transition_steps=_decay_every(train_config),
            decay_rate=train_config.lr_decay, staircase=True),
        temperature=optax.linear_schedule(
            train_config.tau_start, train_config.tau_end, transition_steps=train_config.epochs))
