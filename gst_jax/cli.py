"""What every command shares: the flags (`--scene`, `--protocol`, `--edge-heads`, `--epochs`,
`--seed`, `--workdir`, `--json`, ...), so that each means the same thing everywhere; their
typed configs; and `run`, which turns the library's errors into one-line messages. A flag that
sets a config field takes its type, range or choices and its help from that field's rule
(`gst_jax.config.Rule`, through `add_field_flag`), the rule config.json's checks read too.

One job, though over 400 lines: the shared flags, each with its parser, its help and the config
field it becomes, in one place, so that a flag means one thing in every command."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from gst_jax.config import (
    DETECTION,
    EDGE_HEAD_CHOICES,
    FINE_TUNING,
    SCENES,
    DataConfig,
    ModelConfig,
    TimeGrid,
    TrainConfig,
    describe,
    rules,
)
from gst_jax.data import data_name
from gst_jax.data.protocols import bundled_or_local
from gst_jax.data.readers import UNITS, parse_columns
from gst_jax.errors import USER_ERRORS, DataError, Interrupted
from gst_jax.host_devices import keep_ynnpack_to_matrix_products
from gst_jax.io.interrupts import stops_end_the_process
from gst_jax.private_folders import private_folder

if TYPE_CHECKING:
    from gst_jax.parallel import Devices

_TRAIN_DEFAULTS = TrainConfig()


def positive_int(text: str) -> int:
    """An argparse type: an integer of at least 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


# A flag's Action (`add_field_flag`) or type (`field_type`) names the config field it sets
# here: (config class, field name).
FIELD = "config_field"


def field_type(config_class, name: str) -> Callable[[str], Any]:
    """An argparse type for a config field: the text read as the field's kind and held to its
    rule (`gst_jax.config.Rule`), refused in the rule's words ("must be at least 1, got 0")."""
    rule = rules(config_class)[name]
    read = {int: int, float: float, str: str}[rule.kind]

    def checked(text: str):
        value = read(text)
        if (refused := rule.refusal(value, text)) is not None:
            raise argparse.ArgumentTypeError(refused)
        return value
    checked.__name__ = read.__name__                 # argparse: "invalid int value: 'x'"
    setattr(checked, FIELD, (config_class, name))
    return checked


def add_field_flag(group, flag: str, config_class, name: str, *, default,
                   default_says: str | None = None, also: str = "", **options):
    """A flag that sets the config field `config_class.name`: its type and range or choices,
    and its help, from the field's rule (`also`: words the flag adds, e.g. how it differs);
    `default_says`: what the flag's default means where neither it nor the rule's says it.
    `options` go to argparse (an action, a metavar, or a type or choices narrower than the
    field's, checked by tests/test_config.py to lie within it). Returns the Action."""
    rule = rules(config_class)[name]
    help, rule_says = describe(config_class, name)
    if options.get("action") not in ("store_true", "store_false"):
        if rule.choices is not None:
            options.setdefault("choices", rule.choices)
        elif rule.kind is not str:
            options.setdefault("type", field_type(config_class, name))
    switch = options.get("action") in ("store_true", "store_false")
    said = default_says or rule_says or (None if default is None or switch else f"{default}")
    help += also + (f" (default: {said})" if said is not None else "")
    action = group.add_argument(flag, default=default, help=help, **options)
    setattr(action, FIELD, (config_class, name))
    return action


def node_width(text: str) -> int:
    """An argparse type: a node width (`ModelConfig.node_dim`) that the encoder's heads
    divide."""
    value, heads = field_type(ModelConfig, "node_dim")(text), ModelConfig.encoder_heads
    if value % heads:
        raise argparse.ArgumentTypeError(f"must be a multiple of {heads} (the encoder's heads), "
                                         f"got {value}")
    return value


def count(text: str) -> int:
    """An argparse type: an integer of at least 0."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def positive_float(text: str) -> float:
    """An argparse type: a finite number above 0."""
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def at_least(minimum: int, why: str) -> Callable[[str], int]:
    """An argparse type: an integer of at least `minimum` (`why` says what needs it)."""
    def checked(text: str) -> int:
        if (value := int(text)) < minimum:
            raise argparse.ArgumentTypeError(f"at least {minimum} ({why}), got {value}")
        return value
    return checked


def open_fraction(text: str) -> float:
    """An argparse type: a number strictly between 0 and 1 (a miscoverage alpha: at 0 every
    disc is unbounded, at 1 empty; a fraction of the frames)."""
    value = float(text)
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"must lie strictly between 0 and 1, got {text}")
    return value


def parser(prog: str, doc: str, *, compilation_cache: bool = False
           ) -> argparse.ArgumentParser:
    """A command's parser, described by the first paragraph of its module docstring;
    compilation_cache: the command compiles a model's programs (--compilation-cache)."""
    made = argparse.ArgumentParser(prog=f"python -m {prog}", description=doc.split("\n\n")[0],
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    if compilation_cache:
        add_compilation_cache_flag(made)
    return made


# Compiled programs are kept here across runs (unless JAX_COMPILATION_CACHE_DIR says where):
# a resumed or repeated training compiles nothing it compiled before.
COMPILATION_CACHE = Path.home() / ".cache" / "gst_jax" / "xla"


def use_compilation_cache(directory: str | None = None) -> None:
    """Keep compiled programs in `directory` (--compilation-cache) if given, every program
    however quickly it compiled (`gst_jax.compiles.use_persistent_cache`); else in
    $JAX_COMPILATION_CACHE_DIR if set, else COMPILATION_CACHE, those that took JAX's 1 s.
    Each folder must be this user's alone (`gst_jax.private_folders`: DataError otherwise).

    A command that computes nothing (`data stats`) must not pay for importing jax: where it
    is not imported yet, jax reads the setting from the environment when it is."""
    chosen = directory if directory is not None else (
        os.environ.get("JAX_COMPILATION_CACHE_DIR") or COMPILATION_CACHE)
    path = private_folder(chosen)
    if "jax" in sys.modules:
        from gst_jax.compiles import use_persistent_cache

        use_persistent_cache(path, 0.0 if directory is not None else None)
        return
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(path)
    if directory is not None:
        os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"


def add_compilation_cache_flag(parser: argparse.ArgumentParser) -> None:
    """--compilation-cache DIR, for the commands that compile a model's programs."""
    parser.add_argument("--compilation-cache", metavar="DIR", default=None,
                        help="keep every compiled program in DIR and load it from there in "
                             "later runs, so that a restarted process does not compile again "
                             "(default: $JAX_COMPILATION_CACHE_DIR if set, else "
                             "~/.cache/gst_jax/xla, programs that compiled in over 1 s). It "
                             "holds machine code: it must be yours, writable by no one else")


# Seconds from a stop signal (Ctrl-C, SIGTERM) to the end of a command that has not stopped
# by itself (its main thread inside an XLA compilation); a write in progress completes first.
STOP_GRACE_S = 4.0


def run(command: Callable[[argparse.Namespace], None], parser: argparse.ArgumentParser,
        argv: list[str] | None) -> None:
    """Parse `argv` and run `command`; a user error ends the process with one line, a stop
    signal (Ctrl-C, SIGTERM) with one line and status 130. A process that forces several host
    devices keeps XLA's YNNPACK to its matrix products (`gst_jax.host_devices`)."""
    keep_ynnpack_to_matrix_products()
    args = parser.parse_args(argv)
    warnings.formatwarning = lambda message, *_, **__: f"warning: {message}\n"
    try:
        use_compilation_cache(getattr(args, "compilation_cache", None))
        with stops_end_the_process(STOP_GRACE_S):
            command(args)
    except USER_ERRORS as error:
        raise SystemExit(f"error: {error}") from None
    except KeyboardInterrupt as interrupt:
        # os._exit: the interpreter's shutdown with XLA's threads mid-work can hang and crash.
        say(str(interrupt) if isinstance(interrupt, Interrupted) else "interrupted")
        sys.stdout.flush()
        os._exit(130)
    except BrokenPipeError:       # the reader of stdout left (`| head`): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        raise SystemExit(1) from None
    except OSError as error:      # a full disk, a read-only folder: what, where, why
        where = f"{error.filename}: " if error.filename else ""
        raise SystemExit(f"error: {where}{error.strerror or error}") from None


def add_data_flags(parser: argparse.ArgumentParser, *, of_run: bool = False,
                   fine_tuning: bool = False) -> None:
    """--scene, --protocol, --data-dir. of_run: the defaults are those of the model's run;
    fine_tuning: the command fine-tunes with --init, which has a protocol of its own."""
    group = parser.add_argument_group("data")
    default = "the run's own" if of_run else None
    protocol_default = default or "paper" + (
        f"; {FINE_TUNING['protocol']} when fine-tuning with --init" if fine_tuning else "")
    # --scene names a bundled scene (SCENES, each a scene name the field takes); your own
    # data's name comes from --data.
    add_field_flag(group, "--scene", DataConfig, "scene", default=None if of_run else "eth",
                   choices=SCENES, default_says=default)
    add_field_flag(group, "--protocol", DataConfig, "protocol",
                   default=None if of_run or fine_tuning else "paper",
                   default_says=protocol_default)
    add_field_flag(group, "--data-dir", DataConfig, "data_dir", default=None,
                   default_says=default)
    add_own_data_flags(group)


def add_own_data_flags(group, data_group=None) -> None:
    """--drop-off-grid, --data, --fps, --units, --columns: reading files, and your own files.
    data_group: where --data goes, if not in `group` (a mutually exclusive one)."""
    add_field_flag(group, "--drop-off-grid", DataConfig, "drop_off_grid", default=False,
                   action="store_true")
    add_field_flag(data_group or group, "--data", DataConfig, "data", default=None,
                   metavar="PATH")
    add_field_flag(group, "--fps", DataConfig, "fps", default=None)
    # --units sets DataConfig.scale to one of UNITS' metres per unit (each within its rule).
    group.add_argument("--units", default="m", choices=tuple(UNITS),
                       help="unit of --data's coordinates (default: m)")
    # --columns: a string the readers can parse (column_map), as the field holds it.
    add_field_flag(group, "--columns", DataConfig, "columns", default=None, type=column_map,
                   metavar="F,ID,X,Y")


def add_choice_flags(parser: argparse.ArgumentParser) -> None:
    """`pretrained choose`'s flags: its data (--data and the flags that read it, or --scene;
    their validation split under protocol paper-val, as a fine-tuning's), --models, --samples,
    --seed, --json, --compilation-cache."""
    group = parser.add_argument_group("data (the validation split of protocol paper-val)")
    which = group.add_mutually_exclusive_group(required=True)
    add_field_flag(which, "--scene", DataConfig, "scene", default=None, choices=SCENES,
                   default_says="none: give --data or --scene")
    add_own_data_flags(group, which)
    parser.set_defaults(protocol=FINE_TUNING["protocol"], data_dir=None)
    parser.add_argument("--models", default=None,
                        type=lambda text: [n.strip() for n in text.split(",") if n.strip()],
                        metavar="NAME,...", help="shipped models to compare, "
                        "e.g. hotel_d,crowd_d (default: every shipped model)")
    parser.add_argument("--samples", type=positive_int, default=20,
                        help="K: samples of every window, as evaluate's (default: 20)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the samples (default: 0)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    add_compilation_cache_flag(parser)


def column_map(text: str) -> str:
    """An argparse type: --columns, checked, spaces removed ('frame, id,8,9' -> 'frame,id,8,9')."""
    try:
        parse_columns(text)
    except DataError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix(f"--columns {text}: ")) from None
    return ",".join(item.strip() for item in text.split(","))


def add_sampling_flags(parser: argparse.ArgumentParser) -> None:
    """--split, --samples, --seed, --epoch, --candidates: which windows a model predicts, and
    how."""
    parser.add_argument("--split", default="test", choices=("test", "val", "train", "all"),
                        help="which split; all: every window (default: test)")
    parser.add_argument("--samples", type=positive_int, default=20,
                        help="K: runs of the paper protocol / samples for best-of-K and KDE "
                             "(default: 20)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the samples (default: 0)")
    parser.add_argument("--epoch", type=int, default=None,
                        help="checkpoint epoch (default: latest)")
    add_field_flag(parser, "--candidates", ModelConfig, "candidates", default=None,
                   metavar="K", default_says="the model's own",
                   also="; predicting with K, an evaluation is printed, not written")


def add_windows_flag(parser: argparse.ArgumentParser, *, scoring: bool) -> None:
    """--windows: for a TrajNet++ file, a prediction file of the split's windows, not a
    submission for the file's own scenes (`gst_jax.data.trajnet`); scoring: evaluate's."""
    if scoring:
        help = ("with --predictions: the file holds the split's windows (`predict --windows`); "
                "without, a TrajNet++ file's data is scored as a submission for its own scenes, "
                "by gst_jax's per-pedestrian metrics and by TrajNet++'s evaluator's rules")
    else:
        help = ("for a TrajNet++ file: predict the split's windows, one scene row each (ids "
                "are window indices, every predicted pedestrian, the observed tracks), "
                "instead of a submission for the file's own scenes")
    parser.add_argument("--windows", action="store_true", help=help)


def add_model_flags(parser: argparse.ArgumentParser, *, several_edge_heads: bool = False) -> None:
    """--edge-heads (one n, or a comma-separated list for sweeps), --no-ghost, --output,
    --temporal, the widths and depth, and the time grid (--step, --obs-len, --pred-len)."""
    from gst_jax.model.heads import HEADS  # only commands that build a model load jax

    group = parser.add_argument_group("model")
    m = ModelConfig()
    if several_edge_heads:
        group.add_argument("--edge-heads", default="0,1,2,4,8,16", type=parse_edge_heads,
                           help="comma-separated n to sweep, 0 = full connection "
                                "(default: 0,1,2,4,8,16)")
    else:
        # The paper's n (EDGE_HEAD_CHOICES), each one the field takes.
        add_field_flag(group, "--edge-heads", ModelConfig, "num_edge_heads",
                       default=m.num_edge_heads, type=int, choices=EDGE_HEAD_CHOICES)
    group.add_argument("--no-ghost", action="store_true",
                       help=f"disable {describe(ModelConfig, 'ghost')[0]}")
    # A model's output is one of the model layer's heads (HEADS, which may grow).
    add_field_flag(group, "--output", ModelConfig, "output", default=m.output,
                   choices=tuple(HEADS))
    add_field_flag(group, "--temporal", ModelConfig, "temporal", default=m.temporal)
    add_field_flag(group, "--node-dim", ModelConfig, "node_dim", default=m.node_dim,
                   type=node_width, also="; edges get 2d",
                   default_says=f"{m.node_dim}, docs/MODEL.md; the release's training scripts "
                                "leave its --embedding_size at 64")
    add_field_flag(group, "--encoder-layers", ModelConfig, "encoder_layers",
                   default=m.encoder_layers,
                   default_says=f"{m.encoder_layers}; CrowdNav++'s model has 1")
    add_field_flag(group, "--lstm-dim", ModelConfig, "lstm_hidden", default=m.lstm_hidden)
    add_field_flag(group, "--candidates", ModelConfig, "candidates", default=m.candidates,
                   metavar="K")
    add_field_flag(group, "--attention", ModelConfig, "attention", default=m.attention)
    add_grid_flags(group)


def add_grid_flags(group) -> None:
    """--step, --obs-len, --pred-len: a model's time grid."""
    grid = TimeGrid()
    add_field_flag(group, "--step", TimeGrid, "step_s", default=grid.step_s, metavar="SECONDS",
                   default_says=f"{grid.step_s:g}, the paper's 2.5 Hz; CrowdNav++: 0.25")
    add_field_flag(group, "--obs-len", TimeGrid, "obs_len", default=grid.obs_len)
    add_field_flag(group, "--pred-len", TimeGrid, "pred_len", default=grid.pred_len)


def add_train_flags(parser: argparse.ArgumentParser, *, sweep: bool = False) -> None:
    """The schedule's flags. sweep: --seeds (a count) and a three-way --fully-detected-only."""
    group = parser.add_argument_group("training")
    d = _TRAIN_DEFAULTS
    add_field_flag(group, "--epochs", TrainConfig, "epochs", default=d.epochs)
    # Fine-tuning (--init) has a schedule and a learning rate of its own (FINE_TUNING): left
    # out, these two flags are None, and train_config takes the paper's or fine-tuning's.
    tuned = "" if sweep else "; {} when fine-tuning with --init"
    add_field_flag(group, "--schedule", TrainConfig, "schedule",
                   default=d.schedule if sweep else None,
                   default_says=d.schedule + tuned.format(FINE_TUNING["schedule"]))
    add_field_flag(group, "--batch-size", TrainConfig, "batch_size", default=d.batch_size)
    add_field_flag(group, "--learning-rate", TrainConfig, "learning_rate",
                   default=d.learning_rate if sweep else None,
                   default_says=f"{d.learning_rate}" + tuned.format(FINE_TUNING["learning_rate"]))
    if sweep:
        add_field_flag(group, "--seed", TrainConfig, "seed", default=d.seed,
                       also=" of the first member; also fixes the shared data order")
        group.add_argument("--seeds", type=positive_int, default=1,
                           help="seeds per configuration: seed, seed+1, ... (default: 1)")
        group.add_argument("--fully-detected-only", default="partial", choices=tuple(DETECTION),
                           help="partial: observe everyone (paper default); full: only fully "
                                "detected pedestrians (the paper's 'F'); both (default: partial)")
    else:
        add_field_flag(group, "--seed", TrainConfig, "seed", default=d.seed)
        add_field_flag(group, "--fully-detected-only", TrainConfig, "fully_detected_only",
                       default=False, action="store_true")
        add_field_flag(group, "--score-partial", TrainConfig, "score_partial", default=False,
                       action="store_true")
        add_field_flag(group, "--hide-history", TrainConfig, "hide_history", default=0.0,
                       metavar="P")
        add_field_flag(group, "--init", TrainConfig, "init", default=None, metavar="MODEL")
        add_field_flag(group, "--eval-every", TrainConfig, "eval_every", default=d.eval_every)
    group.add_argument("--no-rotate", action="store_true",
                       help=f"disable {describe(TrainConfig, 'rotate')[0]}")
    add_field_flag(group, "--checkpoint-every", TrainConfig, "checkpoint_every",
                   default=d.checkpoint_every)
    add_field_flag(group, "--max-train-windows", TrainConfig, "max_train_windows", default=0)


def add_device_flags(parser: argparse.ArgumentParser) -> None:
    """--devices, and --coordinator / --num-processes / --process-id for several machines."""
    group = parser.add_argument_group("devices (see docs/scaling.md)")
    group.add_argument("--devices", type=positive_int, default=None,
                       help="use the first N local devices (default: all of them, for a "
                            "sweep the most that split its members evenly; with several "
                            "processes, every device of every process)")
    group.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                       help="join several processes with jax.distributed: the address of "
                            "process 0; 'auto' reads the cluster's environment (Slurm, ...)")
    group.add_argument("--num-processes", type=positive_int, default=None,
                       help="with --coordinator HOST:PORT: how many processes join")
    group.add_argument("--process-id", type=count, default=None,
                       help="with --coordinator HOST:PORT: this process's rank, 0 to N-1")


def devices(args: argparse.Namespace, *, members: int | None = None) -> Devices | None:
    """The devices the flags name; None for one device (the single-device program). For a
    sweep of `members`, by default the most devices that split them evenly."""
    import jax

    from gst_jax import parallel

    if args.coordinator is not None:
        auto = args.coordinator == "auto"
        parallel.join_processes(None if auto else args.coordinator, args.num_processes,
                                args.process_id)
    count = args.devices
    if count is None and members is not None and jax.process_count() == 1:
        count = math.gcd(members, jax.local_device_count())
    chosen = parallel.devices(count)
    return chosen if chosen.count > 1 else None


def add_output_flags(parser: argparse.ArgumentParser, *, workdir_help: str,
                     workdir_default: str | None = None, compilation_cache: bool = False
                     ) -> None:
    """--workdir and --json; with compilation_cache, --compilation-cache too (for a
    subcommand's parser, where `parser(..., compilation_cache=True)` cannot put it)."""
    parser.add_argument("--workdir", default=workdir_default, help=workdir_help)
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    if compilation_cache:
        add_compilation_cache_flag(parser)


def add_humans_flags(parser: argparse.ArgumentParser, *, mix: bool = False) -> None:
    """--humans, --reactive, --num-humans, --shift: how the navigation task's humans walk
    (`simulate.crowdnav.environment.CrowdNav`); with `mix`, left out they mean every
    condition of the training mix (`simulate.crowdnav.crowds.MIX`)."""
    from gst_jax.simulate.crowdnav.environment import NO_SHIFT, POLICY_SHIFT, SPEED_SHIFT, EnvParams

    default = (lambda value: None) if mix else (lambda value: value)
    said = (lambda value: "the mix's") if mix else (lambda value: value)
    parser.add_argument("--humans", choices=("orca", "social-force"), default=default("orca"),
                        help=f"how the humans walk: CrowdNav++'s ORCA or its social force "
                        f"(default: {said('orca')})")
    parser.add_argument("--reactive", action="store_true", default=default(False),
                        help="the humans see the robot (robot.visible)")
    parser.add_argument("--num-humans", type=positive_int, default=default(20),
                        help=f"humans (default: {said(20)})")
    parser.add_argument("--shift", choices=(NO_SHIFT, SPEED_SHIFT, POLICY_SHIFT),
                        default=default(NO_SHIFT), help=f"from {EnvParams.shift_at_s:g} s on, "
                        f"humans {EnvParams.speed_factor:g}x faster (speed) or ORCA ones by "
                        f"social force (policy) (default: {said(NO_SHIFT)})")


def add_prediction_flags(parser: argparse.ArgumentParser) -> None:
    """--model, --regions, --alpha, --adapt, --fresh-tracks: what a simulated robot plans
    against."""
    from gst_jax.adaptation import METHODS
    from gst_jax.simulate.crowdnav.records import DEFAULT_MODEL, REGIONS

    parser.add_argument("--model", default=DEFAULT_MODEL, type=model_spec,
                        help="mpc's GST (default: %(default)s)")
    parser.add_argument("--regions", choices=REGIONS, default="dtaci", help="conformal discs "
                        "around the predictions, none, or decision: no discs, a safety margin "
                        "calibrated online to a rate of near misses (default: dtaci)")
    parser.add_argument("--alpha", type=open_fraction, default=0.1,
                        help="the discs' miscoverage (default 0.1)")
    parser.add_argument("--adapt", choices=("none", *METHODS), default="none",
                        help="correct the predictions online from their delayed scores: the "
                        "crowd's speed scale, or a recursive-least-squares blend of the model "
                        "and constant velocity (default: none)")
    parser.add_argument("--fresh-tracks", action="store_true",
                        help="a replaced human's history starts empty, as a tracker's new "
                        "identity (default: it keeps its predecessor's, as in CrowdNav++)")


def crowd_conditions(args: argparse.Namespace) -> tuple:
    """`add_humans_flags(mix=True)`'s conditions: the mix, or the one the flags name (a flag
    left out taking the task's default)."""
    from gst_jax.simulate.crowdnav.crowds import MIX, Condition

    given = {"human_policy": args.humans and args.humans.replace("-", "_"),
             "reactive": args.reactive, "num_humans": args.num_humans, "shift": args.shift}
    given = {k: v for k, v in given.items() if v is not None}
    return (Condition(**given),) if given else MIX


def model_spec(spec: str | None) -> str | None:
    """A model name that means the same from any working directory (absolute paths)."""
    if spec is None or spec.startswith("pretrained:"):
        return spec
    if Path(spec).exists():                     # a path, ':' in its name or not
        return str(Path(spec).absolute())
    where, colon, member = spec.rpartition(":")
    return str(Path(where).absolute()) + colon + member if colon else str(Path(spec).absolute())


def parse_edge_heads(text: str) -> list[int]:
    """'0,1,4' -> [0, 1, 4], each among EDGE_HEAD_CHOICES (an argparse type)."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}") from None
    choices = ",".join(map(str, EDGE_HEAD_CHOICES))
    if not values or any(v not in EDGE_HEAD_CHOICES for v in values):
        raise argparse.ArgumentTypeError(f"values must be among {choices}, got {text!r}")
    return values


def data_config(args: argparse.Namespace, base: DataConfig | None = None) -> DataConfig:
    """The flags' data config; flags left at None keep `base`'s values (a run's own). Paths
    are stored absolute, so a run reads the same files from any working directory."""
    base = base or DataConfig()
    protocol = args.protocol or (FINE_TUNING["protocol"] if getattr(args, "init", None)
                                 else base.protocol)
    config = dataclasses.replace(
        base, scene=args.scene or base.scene, protocol=protocol,
        data_dir=str(Path(args.data_dir).absolute()) if args.data_dir else base.data_dir,
        drop_off_grid=args.drop_off_grid or base.drop_off_grid)
    if args.scene and not args.data:                     # a bundled scene, not the run's files
        config = dataclasses.replace(config, data=None, fps=None, scale=1.0, columns=None)
    if args.data:
        # Stored absolute, but a path into the bundled data stays relative (found anywhere).
        pattern = args.data if bundled_or_local(args.data) != Path(args.data) else str(
            Path(args.data).absolute())
        config = dataclasses.replace(config, scene=data_name(pattern), data=pattern,
                                     fps=args.fps, scale=UNITS[args.units], columns=args.columns)
    elif args.fps or args.units != "m" or args.columns:
        raise DataError("--fps, --units and --columns describe your own files: give them with "
                        "--data")
    elif config.data:               # named by a model's config.json, not by you: say which
        say(f"data: {config.data} (the model's own, named by its config; --data or --scene "
            "reads others)")
    return config


def model_config(args: argparse.Namespace) -> ModelConfig:
    edge_heads = args.edge_heads if isinstance(args.edge_heads, int) else args.edge_heads[0]
    return ModelConfig(num_edge_heads=edge_heads, ghost=not args.no_ghost,
                       output=args.output, temporal=args.temporal, node_dim=args.node_dim,
                       edge_dim=2 * args.node_dim, encoder_layers=args.encoder_layers,
                       lstm_hidden=args.lstm_dim, candidates=args.candidates,
                       attention=args.attention,
                       **dataclasses.asdict(time_grid(args)))


def time_grid(args: argparse.Namespace) -> TimeGrid:
    return TimeGrid(step_s=args.step, obs_len=args.obs_len, pred_len=args.pred_len)


def train_config(args: argparse.Namespace) -> TrainConfig:
    """The flags' TrainConfig; flags left at None take the paper's defaults, or fine-tuning's
    (`FINE_TUNING`) with --init."""
    defaults = FINE_TUNING if getattr(args, "init", None) else dataclasses.asdict(_TRAIN_DEFAULTS)
    fields = dict(epochs=args.epochs, schedule=args.schedule or defaults["schedule"],
                  batch_size=args.batch_size,
                  learning_rate=args.learning_rate or defaults["learning_rate"], seed=args.seed,
                  rotate=not args.no_rotate, checkpoint_every=args.checkpoint_every,
                  max_train_windows=args.max_train_windows)
    if isinstance(args.fully_detected_only, bool):        # a single run, not a sweep
        fields.update(fully_detected_only=args.fully_detected_only, eval_every=args.eval_every,
                      init=model_spec(args.init), score_partial=args.score_partial,
                      hide_history=args.hide_history)
    return dataclasses.replace(_TRAIN_DEFAULTS, **fields)


def say(text: str) -> None:
    """A status line for the user, on stderr (stdout is the result, e.g. --json)."""
    print(text, file=sys.stderr)
