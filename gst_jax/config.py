"""Typed, frozen configuration for every layer of gst_jax.

Shapes and structural switches live here as static Python values. Hyperparameters that vary
inside one compiled program (temperature, learning rate, the number of active edge heads,
the ghost switch) travel as arrays next to the parameters, never through these classes.
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Literal

ETH_UCY_SCENES = ("eth", "hotel", "univ", "zara1", "zara2")
TRAJNET_SCENES = ("lcas", "wildtrack")
# `crowd`: every file of these seven scenes, each split as in its own scene, so that its train
# split is the union of theirs (the general model a robot loads for an unknown crowd).
CROWD_SCENES = ETH_UCY_SCENES + TRAJNET_SCENES
CROWD = "crowd"
SCENES = CROWD_SCENES + (CROWD,)
PROTOCOLS = ("paper", "paper-val", "loo")
# lstm: the paper's masked LSTM; faster_lstm: gst_updated's (CrowdNav++), whose LSTM steps
# through every observed step (masked inputs, no held state); tcn: the release's readout.
TEMPORAL_MODELS = ("lstm", "faster_lstm", "tcn")
# release: softmax over every entry, times the mask, renormalised (the paper's models; a row
# whose masked entries dominate underflows to zeros); masked: masked entries at -inf before
# the softmax (gst_jax.graph.ATTENTION_WEIGHTS).
ATTENTION_KINDS = ("release", "masked")
# Learning-rate and temperature schedules (gst_jax.training.schedules).
SCHEDULES = ("paper", "compressed", "finetune")
# What fine-tuning (`train --init MODEL`) changes unless told otherwise: a validation split to
# select its epoch on, the model's end temperature and a learning rate ten times below the
# paper's (docs/own-data.md, "Fine-tuning").
FINE_TUNING = {"protocol": "paper-val", "schedule": "finetune", "learning_rate": 1e-4}
# n, the number of edge heads; 0 = full connection (the paper's "F", no selector).
EDGE_HEAD_CHOICES = (0, 1, 2, 4, 8, 16)
# Which pedestrians a sweep observes (its --fully-detected-only): everyone (the paper's
# default), only the fully detected (the paper's "F" baseline), or both side by side.
DETECTION = {"partial": (False,), "full": (True,), "both": (False, True)}
# Gumbel-softmax temperature of every evaluation and prediction (hard samples; docs/MODEL.md 4).
EVAL_TAU = 0.03


@dataclasses.dataclass(frozen=True)
class TimeGrid:
    """The steps a model observes and predicts: `obs_len` observed then `pred_len` predicted,
    `step_s` seconds apart. The paper's: 8 and 12 steps of 0.4 s (3.2 s observed, 4.8 s
    predicted, 2.5 Hz). A model records its grid (`ModelConfig.grid`); data, evaluation,
    prediction files and the simulator follow it."""

    step_s: float = 0.4
    obs_len: int = 8
    pred_len: int = 12

    @property
    def seq_len(self) -> int:
        return self.obs_len + self.pred_len

    @property
    def hz(self) -> float:
        return 1.0 / self.step_s


class _FromDict:
    """`from_dict`: a config from its JSON form (config.json, checkpoints, meta.json). Fields it
    lacks take their defaults; fields a config no longer has (RETIRED) are dropped, so that
    runs written by earlier versions still load, resume and compare."""

    RETIRED: frozenset = frozenset()

    @classmethod
    def from_dict(cls, fields: dict):
        return cls(**{k: v for k, v in fields.items() if k not in cls.RETIRED})


@dataclasses.dataclass(frozen=True)
class DataConfig(_FromDict):
    """Which windows of which files: a scene or your own files, and a split protocol. Windows
    are cut to the time grid of the model that reads them (`TimeGrid`).

    Attributes:
      scene: one of SCENES, or the name of your own `data`.
      protocol: 'paper' (the release's per-file temporal 80/20 split), 'paper-val' (the same,
        with a validation set carved from the end of each file's train windows and the train
        windows overlapping it in time removed) or 'loo' (leave-one-scene-out; ETH/UCY only).
      train_fraction: fraction of each file's windows used for training (paper: 0.8).
      val_fraction: with 'paper-val', fraction of each file's train windows held out.
      data_dir: folder holding `eth_ucy/` and `trajnetpp/`; None = the bundled `data/`.
      drop_off_grid: drop rows whose frame is off a file's grid (counted in a warning)
        instead of refusing the file.
      data: your own files instead of a bundled scene: an absolute path to a file, a folder
        or a glob of text files (`frame ped x y`, or CSV with a header) or TrajNet++ ndjson.
      fps: frame ids per second of `data` (25 for ETH/UCY's video frames, 10 for a 10 Hz
        tracker numbering its samples 0, 1, 2, ...); annotations at a multiple of the model's
        rate are resampled to it, others refused. None: a TrajNet++ file's own rate, else
        annotations taken to be one model step apart.
      scale: metres per unit of `data`'s coordinates.
      columns: which columns of `data`'s text files hold frame, pedestrian id, x and y:
        four comma-separated header names or column numbers counted from 1 (`--columns`,
        e.g. "1,2,8,9" for MOTChallenge rows). None: a header's usual names (frame, id /
        ped / track_id, x, y), else the four columns `frame ped x y`.
    """

    # Windows followed DataConfig's own obs_len / pred_len before they followed the model's.
    RETIRED = frozenset({"obs_len", "pred_len"})

    scene: str = "eth"
    protocol: str = "paper"
    train_fraction: float = 0.8
    val_fraction: float = 0.1
    data_dir: str | None = None
    drop_off_grid: bool = False
    data: str | None = None
    fps: float | None = None
    scale: float = 1.0
    columns: str | None = None

    def __post_init__(self):
        # A scene names files (eval/<scene>-...json) and may come from any config.json: a name,
        # never a path.
        if not isinstance(self.scene, str) or not SCENE_NAME.fullmatch(self.scene):
            raise ValueError(f"scene must be one of {', '.join(SCENES)} or a name of your own "
                             f"data (no / or \\, not starting with . or -, at most 120 "
                             f"characters), got {str(self.scene)[:120]!r}")


# What a scene's name may be: no path separator, no leading '.' or '-' ('..', a hidden file, a
# flag), no control character (a shipped model's scene may describe where its data came from).
SCENE_NAME = re.compile(r"[^/\\\x00-\x1f.-][^/\\\x00-\x1f]{0,119}")


@dataclasses.dataclass(frozen=True)
class ModelConfig(_FromDict):
    """Shapes and structural switches of the Gumbel Social Transformer (docs/MODEL.md 2).

    Attributes:
      node_dim: d, width of node embeddings and of the LSTM input (32).
      edge_dim: d_e = 2d, width of edge embeddings (64).
      max_edge_heads: head slots G of the edge selector's computation: one compiled program
        serves every n dividing G (n itself is traced, e.g. vmapped in sweeps). Parameters do
        not depend on G, so checkpoints move freely between values. 0 = G = max(n, 1), the
        cheapest program for a single n; 16 serves n in {1, 2, 4, 8, 16}.
      num_edge_heads: the default n (0 = full connection, no selector); a traced override
        can be passed to `apply`.
      ghost: default for the ghost agent switch (traced override possible).
      encoder_layers / encoder_heads / encoder_ff_dim: node transformer (3, 8, 128).
      lstm_hidden: hidden width of the masked LSTM (32).
      dropout: dropout rate of selector MLP and encoder (0.1).
      output: the output head (`gst_jax.model.heads.HEADS`): 'deterministic' (GST (D)) or
        'gaussian' (GST (P)).
      temporal: 'lstm' (paper default: recurrent rollout with interaction at every predicted
        step), 'faster_lstm' (the same, but the observation LSTM steps through every observed
        step with masked inputs instead of holding its state: gst_updated's, CrowdNav++'s)
        or 'tcn' (the release's temporal convolution readout: interaction over the observed
        steps only, all predicted steps at once).
      step_s / obs_len / pred_len: the model's time grid (`grid`): steps observed and
        predicted, step_s seconds apart.
      candidates: k, each target's candidate neighbourhood (docs/MODEL.md 2.4): 0 = exact,
        every valid person is a candidate; k > 0 = only the k nearest valid people at that
        step (itself included) and the ghost: the selector and the encoder's attention then
        grow as N k^2 and N k instead of N^3 and N^2. No parameter depends on it, so a model
        trained exactly can predict with candidates (`dataclasses.replace`) and vice versa.
      attention: how the selector's and the encoder's attention and the edge probabilities
        treat masked entries (ATTENTION_KINDS): 'release' (softmax over all, masked and
        renormalised: the paper's models and parity) or 'masked' (masked entries excluded
        before the softmax; no row underflows, and padding cannot change the output). No
        parameter depends on it.
    """

    node_dim: int = 32
    edge_dim: int = 64
    max_edge_heads: int = 0
    num_edge_heads: int = 1
    ghost: bool = True
    encoder_layers: int = 3
    encoder_heads: int = 8
    encoder_ff_dim: int = 128
    lstm_hidden: int = 32
    dropout: float = 0.1
    output: str = "deterministic"
    temporal: Literal["lstm", "faster_lstm", "tcn"] = "lstm"
    step_s: float = TimeGrid.step_s
    obs_len: int = TimeGrid.obs_len
    pred_len: int = TimeGrid.pred_len
    candidates: int = 0
    attention: str = "release"

    def __post_init__(self):
        if self.node_dim % self.encoder_heads:
            raise ValueError(f"node_dim {self.node_dim} must be a multiple of encoder_heads "
                             f"{self.encoder_heads}")
        if self.selector_dim % self.head_slots:
            raise ValueError(f"max_edge_heads {self.head_slots} must divide {self.selector_dim}")
        if self.num_edge_heads and self.head_slots % self.num_edge_heads:
            raise ValueError(f"num_edge_heads {self.num_edge_heads} must divide max_edge_heads "
                             f"{self.max_edge_heads}")
        if self.temporal not in TEMPORAL_MODELS:
            raise ValueError(f"temporal model {self.temporal!r}: expected one of "
                             f"{', '.join(TEMPORAL_MODELS)}")
        if self.attention not in ATTENTION_KINDS:
            raise ValueError(f"attention {self.attention!r}: expected one of "
                             f"{', '.join(ATTENTION_KINDS)}")
        if self.candidates < 0:
            raise ValueError(f"candidates must be 0 (every person) or more, got {self.candidates}")

    @property
    def recurrent(self) -> bool:
        """Whether the prediction is a recurrent rollout (an LSTM), not the TCN readout."""
        return self.temporal != "tcn"

    @property
    def selects_edges(self) -> bool:
        """Whether the program holds an edge selector. One built for full connection alone (n
        = 0, no head slots asked for) has none: its traced n can only be 0."""
        return self.num_edge_heads > 0 or self.max_edge_heads > 0

    @property
    def grid(self) -> TimeGrid:
        return TimeGrid(self.step_s, self.obs_len, self.pred_len)

    @property
    def head_slots(self) -> int:
        """G, the edge selector's head slots (see max_edge_heads)."""
        return self.max_edge_heads or max(self.num_edge_heads, 1)

    @property
    def selector_dim(self) -> int:
        """Width of an augmented edge [x_j | x_i | e_ji] (4d = 128)."""
        return 2 * self.node_dim + self.edge_dim


@dataclasses.dataclass(frozen=True)
class TrainConfig(_FromDict):
    """The optimisation schedule (docs/MODEL.md 3; defaults are the release's).

    Attributes:
      epochs: number of epochs (200).
      schedule: 'paper' (Adam x lr_decay every lr_decay_every epochs, tau annealed over the
        run), 'compressed' (the same shape fitted to `epochs`: x lr_decay every epochs / 4;
        equal to 'paper' at 200 epochs) or 'finetune' (the learning rate constant, tau held at
        tau_end, where a trained model ended). See gst_jax.training.schedules.
      batch_size: scenes averaged per optimiser step (16).
      learning_rate: Adam's initial learning rate (1e-3).
      lr_decay / lr_decay_every: multiply the learning rate by 0.3 every 50 epochs.
      tau_start / tau_end: Gumbel temperature annealed linearly over the epochs, 0.5 -> 0.03.
      rotate: random rotation of every training scene.
      fully_detected_only: train on fully detected pedestrians only (the paper's "F").
      seed: seeds parameters, data order, rotations, Gumbel noise and dropout.
      checkpoint_every: epochs between checkpoints (the last epoch is always saved).
      eval_every: epochs between validation AOE/FOE (0 = never; needs a validation split).
      max_train_windows: use only the first k training windows (smoke tests; 0 = all).
      init: fine-tune: start from this model's parameters (a work directory, DIR:MEMBER or
        pretrained:NAME) instead of a fresh initialisation.
    """

    epochs: int = 200
    schedule: str = "paper"
    batch_size: int = 16
    learning_rate: float = 1e-3
    lr_decay: float = 0.3
    lr_decay_every: int = 50
    tau_start: float = 0.5
    tau_end: float = 0.03
    rotate: bool = True
    fully_detected_only: bool = False
    seed: int = 1000
    checkpoint_every: int = 5
    eval_every: int = 10
    max_train_windows: int = 0
    init: str | None = None

    def __post_init__(self):
        if self.schedule not in SCHEDULES:
            raise ValueError(f"schedule {self.schedule!r}: expected one of {', '.join(SCHEDULES)}")
        for name in ("epochs", "batch_size", "checkpoint_every", "lr_decay_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        for name in ("eval_every", "max_train_windows"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be 0 or more, got {getattr(self, name)}")
        for name in ("learning_rate", "lr_decay", "tau_start", "tau_end"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")


@dataclasses.dataclass(frozen=True)
class Member:
    """One configuration of a sweep: n (0 = full connection), detection, seed."""

    edge_heads: int
    fully_detected_only: bool
    seed: int

    @property
    def detection(self) -> str:
        return "full" if self.fully_detected_only else "partial"

    @property
    def name(self) -> str:
        return f"n{self.edge_heads}-{self.detection}-seed{self.seed}"
