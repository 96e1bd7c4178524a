"""Typed, frozen configuration for every layer of gst_jax.

Shapes and structural switches live here as static Python values. Hyperparameters that vary
inside one compiled program (temperature, learning rate, the number of active edge heads,
the ghost switch) travel as arrays next to the parameters, never through these classes.

Every field's rule (its type, range or choices, and its help) is written beside it, as a
`Rule` in the field's metadata (`setting`): config.json's checks (`gst_jax.model.weights`),
the flags (`gst_jax.cli`) and the configs' own construction (`check`) all read that one rule,
so that a value a flag takes is one a model file may hold, and the reverse.

One job, though over 400 lines: every config's fields, each beside its rule, so that the
rules of one setting are read in one place.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import re
from typing import Any, Literal

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
FINE_TUNING: dict[str, Any] = {"protocol": "paper-val", "schedule": "finetune",
                               "learning_rate": 1e-4}
# n, the number of edge heads; 0 = full connection (the paper's "F", no selector).
EDGE_HEAD_CHOICES = (0, 1, 2, 4, 8, 16)
# Which pedestrians a sweep observes (its --fully-detected-only): everyone (the paper's
# default), only the fully detected (the paper's "F" baseline), or both side by side.
DETECTION = {"partial": (False,), "full": (True,), "both": (False, True)}
# Gumbel-softmax temperature of every evaluation and prediction (hard samples; docs/MODEL.md 4).
EVAL_TAU = 0.03
# What a scene's name may be: no path separator, no leading '.' or '-' ('..', a hidden file, a
# flag), no control character (a shipped model's scene may describe where its data came from).
SCENE_NAME = re.compile(r"[^/\\\x00-\x1f.-][^/\\\x00-\x1f]{0,119}")
# The key of a field's `Rule` in its metadata.
RULE = "gst_jax.rule"


@dataclasses.dataclass(frozen=True)
class Rule:
    """What one config field may hold and what it means: the single rule that config.json's
    checks (`gst_jax.model.weights`), the flags (`gst_jax.cli`) and the config's construction
    (`check`) read. `holds` says whether a value keeps it; `problem` says what a value that does
    not must be, in a file's words ("must be an integer from 1 to 1000"); `refusal` says it
    to the person who typed it ("must be at least 1, got 0").

    Attributes:
      kind: int (not a bool), float (a finite real number, an integer too), bool or str.
      help: the field in a few words, as a flag's help says it before its default; `{name}`
        stands for the default of the config's field `name` (`describe`).
      low / high: the bounds of a number, closed unless low_open / high_open.
      choices: the only values a string may take.
      pattern / pattern_says: what a string must match whole, and that in words.
      optional: None is allowed too.
      default_says: what the default means, where its value does not say it (None, 0 = all).
      always: checked whenever the config is built (`check`); else only where a value comes
        in: a flag, a config.json (a library caller may build what those refuse, and is
        refused where it writes or uses it).
    """

    kind: type
    help: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple | None = None
    pattern: re.Pattern | None = None
    pattern_says: str = ""
    optional: bool = False
    default_says: str | None = None
    always: bool = False

    def holds(self, value: Any, *, strict: bool = False) -> bool:
        """Whether `value` keeps the rule. strict: a number must be a Python int (or float),
        as JSON and a pickle's plain values hold them, not another type (numpy's) that a
        program may hand a config."""
        if value is None:
            return self.optional
        if self.kind is bool:
            return isinstance(value, bool)
        if self.kind is str:
            return (isinstance(value, str)
                    and (self.choices is None or value in self.choices)
                    and (self.pattern is None or self.pattern.fullmatch(value) is not None))
        if strict and type(value) not in ((int,) if self.kind is int else (int, float)):
            return False
        return self._is_number(value) and self._side(value) is None

    def problem(self, value: Any) -> str | None:
        """None where `value` keeps the rule (`strict`ly: a file's values are Python's), else
        what it must be, in the words of a file's check: "must be an integer from 1 to 1000",
        "must be a finite number in (0, 60]"."""
        if self.holds(value, strict=True):
            return None
        null = " or null" if self.optional else ""
        if self.kind is bool:
            return "must be true or false"
        if self.kind is int:
            return f"must be an integer from {self.low} to {self.high}"
        if self.kind is float:
            interval = (f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}"
                        f"{')' if self.high_open else ']'}")
            return f"must be a finite number in {interval}{null}"
        if self.choices is not None:
            return f"must be one of {', '.join(self.choices)}{null}"
        if self.pattern is not None:
            return f"must be {self.pattern_says}{null}"
        return f"must be a string{null}"

    def refusal(self, value: Any, shown: str | None = None) -> str | None:
        """None where `value` keeps the rule, else what it must be and what it is, in the words
        of a person who typed it (a flag, a config built by hand): "must be at least 1, got 0",
        "must be a positive number, got nan". shown: the value as typed (default: its repr, a
        string's first 120 characters)."""
        if self.holds(value):
            return None
        if shown is None:
            shown = (repr(str(value)[:120]) if self.kind is str or not self._is_number(value)
                     else _shown_number(value))
        if self.kind in (int, float) and self._is_number(value):
            return f"must be {self._side(value)}, got {shown}"
        says = {bool: "true or false", int: "an integer", float: "a number",
                str: "a string"}[self.kind]
        if self.kind is str and self.choices is not None:
            says = f"one of {', '.join(self.choices)}"
        elif self.kind is str and self.pattern is not None:
            says = self.pattern_says
        return f"must be {says}{' or None' if self.optional else ''}, got {shown}"

    def _is_number(self, value: Any) -> bool:
        wanted = numbers.Integral if self.kind is int else numbers.Real
        return isinstance(value, wanted) and not isinstance(value, bool)

    def _side(self, value) -> str | None:
        """None where a number is within the bounds, else the bound it passes, in words: "a
        positive number", "0 or more", "at least 1", "at most 60"; NaN passes the low one."""
        if self.low is not None and not (value > self.low if self.low_open
                                         else value >= self.low):
            if self.low == 0:
                return "a positive number" if self.low_open else "0 or more"
            return f"{'above' if self.low_open else 'at least'} {_bound(self.low)}"
        if self.high is not None and not (value < self.high if self.high_open
                                          else value <= self.high):
            return f"{'below' if self.high_open else 'at most'} {_bound(self.high)}"
        if not (isinstance(value, numbers.Integral) or math.isfinite(value)):
            return "a finite number"
        return None


def _bound(bound: float) -> str:
    return str(bound) if isinstance(bound, int) else f"{bound:g}"


def _shown_number(value) -> str:
    """A number as a refusal shows it: an integer of 10^5000 without writing its digits
    (Python refuses to write integers of more than 4300 digits)."""
    if isinstance(value, numbers.Integral) and int(value).bit_length() > 64:
        return f"{'-' if value < 0 else ''}an integer of {int(value).bit_length()} bits"
    return repr(value)


def setting(default: Any, help: str, *, kind: type | None = None, **rule) -> Any:
    """A config field with its default and its `Rule` (kind: the default's type unless
    given; the rest: `Rule`'s attributes)."""
    return dataclasses.field(
        default=default, metadata={RULE: Rule(kind or type(default), help, **rule)})


def same_as(config_class, name: str) -> Any:
    """A field with the default and the rule of `config_class`'s field `name` (ModelConfig's
    time grid is TimeGrid's)."""
    field = {f.name: f for f in dataclasses.fields(config_class)}[name]
    return dataclasses.field(default=field.default, metadata=field.metadata)


def rules(config_class) -> dict[str, Rule]:
    """{field name: its Rule} of a config class (or instance), in the fields' order."""
    return {f.name: f.metadata[RULE] for f in dataclasses.fields(config_class)
            if RULE in f.metadata}


def describe(config_class, name: str) -> tuple[str, str | None]:
    """A field's help and what its default means (`Rule.default_says`, None where its value
    says it), each `{field}` in them filled with that field's default."""
    defaults = {f.name: f.default for f in dataclasses.fields(config_class)}
    rule = rules(config_class)[name]
    says = None if rule.default_says is None else rule.default_says.format(**defaults)
    return rule.help.format(**defaults), says


def check(config, names: tuple[str, ...] | None = None) -> None:
    """The one validation of a config: ValueError naming the first field out of its rule, its
    rule and its value ("epochs must be at least 1, got 0"). names: the fields to check
    (default: those whose rule is `always`, as construction does; `tuple(rules(config))`:
    every field)."""
    for name, rule in rules(config).items():
        if (rule.always if names is None else name in names):
            if (refused := rule.refusal(getattr(config, name))) is not None:
                raise ValueError(f"{name} {refused}")


# The ranges below stop absurd values before any work is spent on them. The time grid, the
# dropout rate, the neighbourhood and the switches shape no tensor: their ranges are all that
# keeps a wrong value out of a model file (a horizon of 10^6 steps would be compiled and run;
# 1000 steps is minutes of walking at any step). A model's widths and depths are checked
# against its tensors too; their bounds are far beyond any model of this kind (the paper's:
# d = 32, three layers): a depth of 10^6 would be traced layer by layer.
MAX_STEPS = 1000
# Epochs, scenes per step, epochs between checkpoints: far beyond any training.
MAX_COUNT = 10**6
# Learning rates, decays and temperatures: positive and at most this.
MAX_RATE = 1e3
# A time step (s): a millisecond is beyond any tracker's rate (1e-300 s would make every
# timestamp a jump of astronomically many steps); a minute, beyond any walk worth predicting.
MIN_STEP_S = 1e-3
MAX_STEP_S = 60


@dataclasses.dataclass(frozen=True)
class TimeGrid:
    """The steps a model observes and predicts: `obs_len` observed then `pred_len` predicted,
    `step_s` seconds apart. The paper's: 8 and 12 steps of 0.4 s (3.2 s observed, 4.8 s
    predicted, 2.5 Hz). A model records its grid (`ModelConfig.grid`); data, evaluation,
    prediction files and the simulator follow it."""

    step_s: float = setting(
        0.4, "the model's time step: data at other rates are resampled to it",
        low=MIN_STEP_S, high=MAX_STEP_S)
    obs_len: int = setting(8, "observed steps", low=1, high=MAX_STEPS)
    pred_len: int = setting(12, "predicted steps", low=1, high=MAX_STEPS)

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
        rate keep every k-th, others down to half its rate are interpolated to its steps
        (`data.readers.to_model_rate`). None: a TrajNet++ file's own rate, else annotations
        taken to be one model step apart.
      scale: metres per unit of `data`'s coordinates.
      columns: which columns of `data`'s text files hold frame, pedestrian id, x and y:
        four comma-separated header names or column numbers counted from 1 (`--columns`,
        e.g. "1,2,8,9" for MOTChallenge rows). None: a header's usual names (frame, id /
        ped / track_id, x, y), else the four columns `frame ped x y`.
    """

    # Windows followed DataConfig's own obs_len / pred_len before they followed the model's.
    RETIRED = frozenset({"obs_len", "pred_len"})

    # A scene names files (eval/<scene>-...json) and may come from any config.json: a name,
    # never a path; checked whenever a DataConfig is built (issue 94).
    scene: str = setting(
        "eth", "dataset: an ETH/UCY scene, a TrajNet++ crowd, or crowd: all seven, each file "
        "split as in its scene", pattern=SCENE_NAME, always=True,
        pattern_says=f"one of {', '.join(SCENES)} or a name of your own data (no / or \\, not "
                     "starting with . or -, at most 120 characters)")
    # Not checked on construction: data.protocols refuses an unknown one where it splits.
    protocol: str = setting(
        "paper", "paper: the release's per-file temporal 80/20 split; paper-val: the same with "
        "a validation set carved from the end of each file's train windows; loo: "
        "leave-one-scene-out (ETH/UCY only)", choices=PROTOCOLS)
    train_fraction: float = setting(
        0.8, "fraction of each file's windows used for training", low=0, low_open=True, high=1)
    val_fraction: float = setting(
        0.1, "with paper-val, fraction of each file's train windows held out", low=0, high=1,
        high_open=True)
    data_dir: str | None = setting(None, "folder holding eth_ucy/ and trajnetpp/", kind=str,
                                   optional=True, default_says="the bundled data/")
    drop_off_grid: bool = setting(
        False, "drop rows whose frame is off their file's frame grid (a warning counts them) "
        "instead of refusing the file")
    data: str | None = setting(
        None, "your own data instead of a bundled scene: a file, a folder or a glob of text "
        "files ('frame ped x y', or a tracker's CSV with a header) or TrajNet++ ndjson (runs "
        "and labels take its name)", kind=str, optional=True)
    fps: float | None = setting(
        None, "frame ids per second of --data (e.g. 10 for a 10 Hz tracker numbering samples "
        "0, 1, 2...); a multiple of the model's rate (2.5 Hz for the paper's) keeps every "
        "k-th row, other rates down to half the model's are interpolated to its steps",
        kind=float, low=0, low_open=True, high=10_000,
        optional=True, default_says="an ndjson file's own rate, else rows one model step apart")
    scale: float = setting(1.0, "metres per unit of --data's coordinates", low=0,
                           low_open=True, high=1e6)
    columns: str | None = setting(
        None, "which columns of --data's text files hold frame, pedestrian id, x and y: header "
        "names or numbers counted from 1, e.g. 1,2,8,9 for MOTChallenge's frame,id,bb_left,"
        "bb_top,bb_width,bb_height,conf,x,y,z", kind=str, optional=True,
        default_says="a header's frame, id/ped/track_id, x, y; else the four columns frame "
                     "ped x y")

    def __post_init__(self):
        check(self)


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

    node_dim: int = setting(32, "d, the width of node embeddings and of the LSTM input",
                            low=1, high=4096)
    edge_dim: int = setting(64, "d_e, the width of edge embeddings", low=1, high=8192)
    max_edge_heads: int = setting(
        0, "G, the edge selector's head slots (0 = max(n, 1))", low=0, high=1024)
    num_edge_heads: int = setting(
        1, "n, the most neighbours each pedestrian attends to; 0 = full connection, no "
        "Gumbel selector", low=0, high=1024)
    ghost: bool = setting(True, "the ghost agent (the 'attend to nobody' neighbour)")
    encoder_layers: int = setting(3, "node transformer layers", low=1, high=64)
    encoder_heads: int = setting(8, "the node transformer's attention heads", low=1, high=1024)
    encoder_ff_dim: int = setting(128, "the node transformer's feed-forward width", low=1,
                                  high=65536)
    lstm_hidden: int = setting(32, "the LSTM's hidden width", low=1, high=4096)
    dropout: float = setting(0.1, "dropout rate of the selector's MLP and the encoder", low=0,
                             high=1, high_open=True)
    # Its choices are the heads of gst_jax.model.heads.HEADS, a registry of the model layer
    # (a test adds one): config.json's check and --output read them there, and building a
    # model refuses another (heads.head).
    output: str = setting(
        "deterministic", "the output head: deterministic = GST (D), displacements; gaussian = "
        "GST (P), bivariate Gaussians")
    temporal: Literal["lstm", "faster_lstm", "tcn"] = setting(
        "lstm", "lstm: recurrent rollout, interacting at every predicted step (paper); "
        "faster_lstm: the same with gst_updated's (CrowdNav++'s) observation LSTM, which steps "
        "through undetected steps too; tcn: the release's temporal convolution readout of the "
        "observed steps", choices=TEMPORAL_MODELS, always=True)
    step_s: float = same_as(TimeGrid, "step_s")
    obs_len: int = same_as(TimeGrid, "obs_len")
    pred_len: int = same_as(TimeGrid, "pred_len")
    candidates: int = setting(
        0, "each pedestrian's candidate neighbours (docs/MODEL.md 2.4): its K nearest at each "
        "step (itself included), for crowds of hundreds; 0 = everyone, the exact model",
        low=0, high=1_000_000, always=True)
    attention: str = setting(
        "release", "release: the paper's attention (softmax over everyone, masked, "
        "renormalised; a row can underflow to zeros); masked: masked entries excluded before "
        "the softmax", choices=ATTENTION_KINDS, always=True)

    def __post_init__(self):
        if self.node_dim % self.encoder_heads:
            raise ValueError(f"node_dim {self.node_dim} must be a multiple of encoder_heads "
                             f"{self.encoder_heads}")
        if self.selector_dim % self.head_slots:
            raise ValueError(f"max_edge_heads {self.head_slots} must divide {self.selector_dim}")
        if self.num_edge_heads and self.head_slots % self.num_edge_heads:
            raise ValueError(f"num_edge_heads {self.num_edge_heads} must divide max_edge_heads "
                             f"{self.max_edge_heads}")
        check(self)

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
      score_partial: GST (P)'s loss scores the partially detected pedestrians too, each at the
        steps its future exists. The release scores only the fully detected, so its models
        never learn to predict a person seen for part of the observation (a robot's sensor
        range makes many); a GST (D) loss scores them already.
      hide_history: the chance that each training pedestrian's history is cut to start at a
        random observed step (1 .. obs_len - 2), so that partially detected people are common
        in training where the data has few (`augment.hide_history`).
      seed: seeds parameters, data order, rotations, Gumbel noise and dropout.
      checkpoint_every: epochs between checkpoints (the last epoch is always saved).
      eval_every: epochs between validation AOE/FOE (0 = never; needs a validation split).
      max_train_windows: use only the first k training windows (smoke tests; 0 = all).
      init: fine-tune: start from this model's parameters (a work directory, DIR:MEMBER or
        pretrained:NAME) instead of a fresh initialisation.
    """

    epochs: int = setting(200, "number of epochs", low=1, high=MAX_COUNT, always=True)
    schedule: str = setting(
        "paper", "paper: learning rate x{lr_decay} every {lr_decay_every} epochs; compressed: "
        "x{lr_decay} every epochs/4 (the paper's shape fitted to --epochs; the same at 200). "
        "Both anneal tau {tau_start} -> {tau_end} over the run. finetune: a constant learning "
        "rate, tau held at {tau_end}", choices=SCHEDULES, always=True)
    batch_size: int = setting(16, "scenes averaged per optimiser step", low=1, high=MAX_COUNT,
                              always=True)
    learning_rate: float = setting(
        1e-3, "initial Adam learning rate, decayed as --schedule says", low=0, low_open=True,
        high=MAX_RATE, always=True)
    lr_decay: float = setting(0.3, "the learning rate's factor at each decay", low=0,
                              low_open=True, high=MAX_RATE, always=True)
    lr_decay_every: int = setting(50, "epochs between decays of the learning rate", low=1,
                                  high=MAX_COUNT, always=True)
    tau_start: float = setting(0.5, "Gumbel temperature of the first epoch", low=0,
                               low_open=True, high=MAX_RATE, always=True)
    tau_end: float = setting(0.03, "Gumbel temperature of the last epoch", low=0,
                             low_open=True, high=MAX_RATE, always=True)
    rotate: bool = setting(True, "random rotation of every training scene")
    fully_detected_only: bool = setting(
        False, "drop partially detected pedestrians (the paper's 'F' baseline)")
    score_partial: bool = setting(
        False, "GST (P)'s loss scores every predicted pedestrian at the steps its future "
        "exists, not only the fully detected (the release's)")
    hide_history: float = setting(
        0.0, "the chance that a training pedestrian is seen only from a random observed step "
        "on (a person who just came into view)", low=0.0, high=1.0)
    seed: int = setting(1000, "random seed", low=-2**63, high=2**63 - 1, always=True)
    checkpoint_every: int = setting(5, "epochs between checkpoints", low=1, high=MAX_COUNT,
                                    always=True)
    eval_every: int = setting(
        10, "epochs between validation AOE/FOE, with a protocol that has a validation split",
        low=0, high=MAX_COUNT, always=True, default_says="{eval_every}; 0 = never")
    max_train_windows: int = setting(
        0, "train on the first k windows only, for smoke tests", low=0, high=10**12, always=True,
        default_says="all")
    init: str | None = setting(
        None, "fine-tune: start from this model's parameters (a work directory, "
        "SWEEP_DIR:MEMBER or pretrained:NAME); the epoch with the best validation AOE (the "
        "starting model's included) is kept", kind=str, optional=True)

    def __post_init__(self):
        check(self)


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
