"""Work directories, the only module that knows their layout, and how a model is named.

    <workdir>/config.json                 the run's configuration (model, data, train[, members])
    <workdir>/checkpoints/<epoch>/        orbax: the training state and the config
    <workdir>/metrics.jsonl               one JSON line per epoch (with the code that trained it)
    <workdir>/summary.json                the training's summary, once it has finished
    <workdir>/eval/<scene>-<protocol>-<split>-e<epoch>.json, .md    evaluations
    <workdir>/figures/                    figures of `python -m gst_jax.plot`
    <workdir>/results.json, .csv, .md     a sweep's evaluation of its members

A model is named by a work directory (or one of its `checkpoints/<epoch>`), by
`SWEEP_DIR:MEMBER` for one member of a sweep, or by `pretrained:NAME` for a shipped model.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple, Sequence

import jax
import numpy as np
import orbax.checkpoint as ocp

from gst_jax import pretrained
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.training.members import Member, member_config, stacked_shape, unstack
from gst_jax.training.state import abstract_train_state


# Where commands put work directories unless told (--workdir), relative to the current folder.
RUNS = Path("runs")


class RunError(Exception):
    """A work directory or model name that cannot be used; the message says why."""


class Restored(NamedTuple):
    """A checkpoint read back: the state, the run's config, the metrics records up to its
    epoch (one per epoch), and the epoch."""

    state: Any
    config: dict
    records: list
    epoch: int


class Checkpointer:
    """Saves `{state, config, metrics}` under `<workdir>/checkpoints/<epoch>`.

    Saving is synchronous and refuses a non-finite state: a checkpoint that `save` returned
    from is complete on disk, so a process killed at any later moment resumes from it. Its
    files' SHA-256 is recorded in `checkpoints/checksums.json`; `restore` verifies it and,
    with `fall_back`, goes back to the newest checkpoint that is intact (with a warning).
    """

    def __init__(self, directory: Path, max_to_keep: int = 3, *, create: bool = True):
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=create,
                                               enable_async_checkpointing=False)
        self._directory = directory.absolute()
        self._manager = ocp.CheckpointManager(self._directory, options=options)
        self._checksums = self._directory / "checksums.json"

    @property
    def latest_epoch(self) -> int | None:
        return self._manager.latest_step()

    def save(self, epoch: int, state: Any, config: dict, records: list) -> None:
        """Save and checksum `epoch`; a Ctrl-C meanwhile takes effect once it is complete."""
        if not all(bool(np.all(np.isfinite(leaf))) for leaf in jax.tree.leaves(state)
                   if np.issubdtype(leaf.dtype, np.floating)):
            raise RunError(f"refusing to save a non-finite training state (epoch {epoch})")
        with _interrupts_deferred():
            self._manager.save(epoch, args=ocp.args.Composite(
                state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(config),
                metrics=ocp.args.JsonSave(records)))
            self._manager.wait_until_finished()
            if jax.process_index() != 0:            # the checksums are written once
                return
            checksums = self._read_checksums()
            checksums[str(epoch)] = self._checksum(epoch)
            kept = {str(e) for e in self._manager.all_steps()}
            _write_atomically(self._checksums, json.dumps(
                {e: c for e, c in checksums.items() if e in kept}, indent=1))

    def restore(self, like_state: Any, epoch: int | None = None, *,
                fall_back: bool = False) -> Restored:
        """Restore `epoch` (default: the latest); `like_state` (arrays or their abstract
        shapes) gives the tree structure and dtypes. With `fall_back`, a checkpoint that fails
        its checksum or cannot be read is skipped for the one before it. The arrays come back
        on this process's first device, whatever devices saved them."""
        here = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        abstract = jax.tree.map(
            lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=here), like_state)
        candidates = [epoch] if epoch is not None else sorted(self._manager.all_steps(),
                                                              reverse=True)
        problems = []
        for candidate in candidates:
            problem = self._verify(candidate)
            if problem is None:
                try:
                    restored = self._manager.restore(candidate, args=ocp.args.Composite(
                        state=ocp.args.StandardRestore(abstract), config=ocp.args.JsonRestore(),
                        metrics=ocp.args.JsonRestore()))
                except Exception as error:  # orbax raises many kinds on damaged files
                    problem = f"unreadable ({type(error).__name__})"
            if problem is None:
                if problems:
                    warnings.warn(f"{self._directory}: using the checkpoint of epoch "
                                  f"{candidate}; skipped " + "; ".join(problems), stacklevel=2)
                return Restored(restored.state, restored.config, list(restored.metrics),
                                candidate)
            problems.append(f"epoch {candidate}: {problem}")
            if not fall_back:
                break
        raise RunError(f"no usable checkpoint in {self._directory}: " + "; ".join(problems)
                       if problems else f"no checkpoint in {self._directory}")

    def read_config(self, epoch: int | None = None) -> dict:
        """The JSON config stored with checkpoint `epoch`, by default the newest readable one
        (arrays untouched)."""
        epochs = [epoch] if epoch is not None else sorted(self._manager.all_steps(), reverse=True)
        for epoch in epochs:
            try:
                return self._manager.restore(epoch, args=ocp.args.Composite(
                    config=ocp.args.JsonRestore())).config
            except Exception:  # a damaged checkpoint: the one before it may do
                continue
        raise RunError(f"no readable checkpoint in {self._directory}")

    def discard_after(self, epoch: int) -> None:
        """Delete the checkpoints of later epochs (damaged ones that a resume skipped)."""
        for later in [e for e in self._manager.all_steps() if e > epoch]:
            self._manager.delete(later)

    def copy_latest(self, directory: Path) -> int | None:
        """Copy the newest checkpoint, with its checksum, into a new checkpoint `directory`;
        returns its epoch, or None when there is none."""
        epoch = self.latest_epoch
        if epoch is None:
            return None
        shutil.copytree(self._directory / str(epoch), directory / str(epoch))
        (directory / "checksums.json").write_text(json.dumps(
            {str(epoch): self._read_checksums()[str(epoch)]}, indent=1))
        return epoch

    def close(self) -> None:
        self._manager.close()

    def _checksum(self, epoch: int) -> str:
        digest = hashlib.sha256()
        folder = self._directory / str(epoch)
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            digest.update(str(path.relative_to(folder)).encode())
            digest.update(path.read_bytes())
        return digest.hexdigest()

    def _read_checksums(self) -> dict:
        try:
            return json.loads(self._checksums.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return {}

    def _verify(self, epoch: int) -> str | None:
        """None if the checkpoint's files match the checksum recorded when it was saved (or
        none was recorded: a crash between the save and the record); else the problem."""
        expected = self._read_checksums().get(str(epoch))
        if expected is not None and expected != self._checksum(epoch):
            return "its files do not match the checksum recorded when it was saved"
        return None


@functools.cache
def code_version() -> str:
    """The git commit of this gst_jax checkout ('+dirty' when gst_jax/ has uncommitted
    changes), recorded with every epoch so that a result names the code that trained it;
    outside a git checkout, $GST_JAX_CODE_VERSION where set (a tree copied to a cluster can
    name the commit it was copied from), else 'gst_jax <version>' (a bare tree says so)."""
    root = Path(__file__).resolve().parents[1]
    git = ["git", "-C", str(root)]
    try:
        commit = subprocess.run([*git, "rev-parse", "--short=10", "HEAD"], capture_output=True,
                                text=True, check=True, timeout=10).stdout.strip()
        changes = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no", "--",
                                  "gst_jax"], capture_output=True, text=True, check=True,
                                 timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        if named := os.environ.get("GST_JAX_CODE_VERSION"):
            return named
        from importlib.metadata import PackageNotFoundError, version
        try:
            return f"gst_jax {version('gst_jax')}"
        except PackageNotFoundError:                # a copied source tree on PYTHONPATH
            return "gst_jax (source tree without git)"
    return commit + ("+dirty" if changes else "")


def _sigint_is_ours() -> bool:
    """Whether this thread may handle SIGINT: the main thread, unless the process ignores it
    (a background job of a script)."""
    return (threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN)


@contextlib.contextmanager
def _interrupts_deferred() -> Iterator[None]:
    """Hold back SIGINT (Ctrl-C, `timeout -s INT`) inside the block and raise it at its end:
    interrupted inside orbax's save, the main thread would leave orbax's writer threads to
    fail at exit with a traceback and a half-written checkpoint. A SIGINT the process ignores
    (a background job of a script) stays ignored."""
    if not _sigint_is_ours():
        yield
        return
    received = []
    previous = signal.signal(signal.SIGINT, lambda *_: received.append(True))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        raise KeyboardInterrupt


@contextlib.contextmanager
def interrupts_noticed() -> Iterator[Callable[[], None]]:
    """Inside the block SIGINT raises KeyboardInterrupt as usual and is also remembered; call
    the yielded check at safe points (after each training step) to raise a remembered one.
    Python swallows an exception raised in a garbage-collection callback ("Exception ignored
    in _xla_gc_callback"), so a Ctrl-C that lands in JAX's would otherwise be lost and the
    run go on (and print "Exception ignored ... KeyboardInterrupt", which is kept quiet here).
    A SIGINT the process ignores stays ignored."""
    received = []

    def check() -> None:
        if received:
            received.clear()
            raise KeyboardInterrupt

    if not _sigint_is_ours():
        yield check
        return

    def remember_and_raise(signum, frame):
        received.append(True)
        raise KeyboardInterrupt

    def report_unless_interrupt(unraisable) -> None:
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            previous_hook(unraisable)

    previous, previous_hook = signal.signal(signal.SIGINT, remember_and_raise), sys.unraisablehook
    sys.unraisablehook = report_unless_interrupt
    try:
        yield check
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = previous_hook


def _write_atomically(path: Path, text: str) -> None:
    temporary = path.with_suffix(path.suffix + ".tmp")
    temporary.write_text(text)
    os.replace(temporary, path)


def run_config(model_config: ModelConfig, data_config: DataConfig, train_config: TrainConfig,
               members: Sequence[Member] | None = None) -> dict:
    """The JSON description of a run (or sweep), stored in its work dir and checkpoints."""
    config = {"model": dataclasses.asdict(model_config), "data": dataclasses.asdict(data_config),
              "train": dataclasses.asdict(train_config)}
    if members is not None:
        config["members"] = [dataclasses.asdict(m) for m in members]
    return config


def same_run(config: dict, other: dict) -> bool:
    """Whether two run configs train the same thing. A field missing from a config (one
    written before the field existed) has its default value. The checkpoint cadence says only
    how often the run is saved, so a resumed run may change it (e.g. to save every epoch of
    a long run that has to be continued over several sittings)."""
    def identity(c: dict) -> dict:
        train = {k: v for k, v in c["train"].items() if k != "checkpoint_every"}
        return {**c, "model": {**_DEFAULTS["model"], **c["model"]},
                "data": {**_DEFAULTS["data"], **c["data"]},
                "train": {**_DEFAULTS["train"], **train}}
    return identity(config) == identity(other)


_DEFAULTS = {"model": dataclasses.asdict(ModelConfig()), "data": dataclasses.asdict(DataConfig()),
             "train": {k: v for k, v in dataclasses.asdict(TrainConfig()).items()
                       if k != "checkpoint_every"}}


def run_name(data_config: DataConfig, model_config: ModelConfig,
             train_config: TrainConfig) -> str:
    """A work directory name that identifies a run, so the same command finds it to resume."""
    parts = [data_config.scene, data_config.protocol,
             "d" if model_config.output == "deterministic" else "p",
             f"n{model_config.num_edge_heads}"]
    if not model_config.ghost:
        parts.append("noghost")
    if model_config.temporal != "lstm":
        parts.append(model_config.temporal)
    if model_config.node_dim != ModelConfig.node_dim:
        parts.append(f"d{model_config.node_dim}")
    if train_config.fully_detected_only:
        parts.append("fd")
    if train_config.init:
        parts.append("from-" + Path(train_config.init.replace(":", "-")).name)
    if train_config.schedule != TrainConfig.schedule:
        parts.append(train_config.schedule)
    parts += [f"e{train_config.epochs}", f"seed{train_config.seed}"]
    return "-".join(parts)


def sweep_name(data_config: DataConfig, train_config: TrainConfig) -> str:
    """The default work directory name of a sweep."""
    schedule = "" if train_config.schedule == TrainConfig.schedule else f"-{train_config.schedule}"
    return f"sweep-{data_config.scene}{schedule}-e{train_config.epochs}"


class WorkDir:
    """The files of one work directory (see the module docstring for the layout).

    With several processes (`gst_jax.parallel`), process 0 alone writes the files that are
    written once (config, metrics, summary, evaluations); the checkpoints are written by
    all, through orbax's multi-process path.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)

    @property
    def writes(self) -> bool:
        """Whether this process writes the files written once (asked when writing: jax's
        processes must be joined before jax is first used)."""
        return jax.process_index() == 0

    def __repr__(self) -> str:
        return f"WorkDir({str(self.path)!r})"

    @property
    def metrics_path(self) -> Path:
        return self.path / "metrics.jsonl"

    @property
    def figures(self) -> Path:
        return self.path / "figures"

    def prepare(self, config: dict) -> None:
        """Create the work dir, or check that an existing one belongs to the same run (its
        config.json and, should that be gone, the config stored with its checkpoints)."""
        config_path = self.path / "config.json"
        if config_path.exists():
            stored = json.loads(config_path.read_text())
            if not same_run(stored, config):
                raise RunError(f"{self.path} holds a run with a different configuration "
                               f"({config_path}); choose another --workdir or delete it")
            if stored != config and self.writes:        # a new checkpoint cadence
                config_path.write_text(json.dumps(config, indent=2) + "\n")
            return
        if (self.path / "checkpoints").is_dir():
            checkpointer = self.checkpointer(create=False)
            try:
                stored = (config if checkpointer.latest_epoch is None
                          else checkpointer.read_config())
            finally:
                checkpointer.close()
            if not same_run(stored, config):
                raise RunError(f"{self.path} holds checkpoints of a run with a different "
                               "configuration (its config.json is missing); choose another "
                               "--workdir or delete it")
        self.path.mkdir(parents=True, exist_ok=True)
        if self.writes:
            config_path.write_text(json.dumps(config, indent=2) + "\n")

    def checkpointer(self, *, create: bool = True) -> Checkpointer:
        """The run's checkpoints; `create=False` reads only and fails without creating
        anything where there are none."""
        directory = self.path / "checkpoints"
        if not create and not directory.is_dir():
            raise RunError(f"no checkpoint in {self.path} (expected {directory}/<epoch>)")
        return Checkpointer(directory, create=create)

    def read_metrics(self) -> list[dict]:
        """The per-epoch records of metrics.jsonl, in order ([] before the first epoch)."""
        if not self.metrics_path.exists():
            return []
        return [json.loads(line) for line in self.metrics_path.read_text().splitlines()
                if line.strip()]

    def append_metrics(self, record: dict) -> None:
        if not self.writes:
            return
        with self.metrics_path.open("a") as f:
            f.write(json.dumps(record) + "\n")

    def write_metrics(self, records: list[dict]) -> None:
        """Replace metrics.jsonl by `records` (a resume: those of its checkpoint, which drop
        what a killed run wrote after it and restore what it did not get to write)."""
        if self.writes:
            lines = "".join(json.dumps(r) + "\n" for r in records)
            _write_atomically(self.metrics_path, lines)

    def park(self, destination: Path) -> int | None:
        """Copy the config and the newest checkpoint to `destination`, a work directory from
        which training continues on another machine; returns the checkpoint's epoch, or None
        before the first checkpoint."""
        if not (self.path / "checkpoints").is_dir():
            return None
        checkpointer = self.checkpointer(create=False)
        try:
            if checkpointer.latest_epoch is None:
                return None
            shutil.rmtree(destination, ignore_errors=True)
            epoch = checkpointer.copy_latest(destination / "checkpoints")
            shutil.copy2(self.path / "config.json", destination / "config.json")
            return epoch
        finally:
            checkpointer.close()

    def latest_checkpoint(self) -> int | None:
        """The epoch of the newest checkpoint, or None before the first (creates nothing)."""
        if not (self.path / "checkpoints").is_dir():
            return None
        checkpointer = self.checkpointer(create=False)
        try:
            return checkpointer.latest_epoch
        finally:
            checkpointer.close()

    def code_versions(self) -> list[str]:
        """The code versions that trained the run's epochs, in order of first use."""
        return list(dict.fromkeys(r["code"] for r in self.read_metrics() if "code" in r))

    def training_time_s(self) -> float:
        """Sum of the epoch times: the training's wall time across resumes."""
        return sum(r.get("epoch_time_s", 0.0) for r in self.read_metrics())

    def write_summary(self, summary: dict) -> None:
        if self.writes:
            (self.path / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")

    def evaluation_path(self, data_config: DataConfig, split: str, epoch: int) -> Path:
        """eval/<scene>-<protocol>-<split>-e<epoch>.json (the .md beside it)."""
        return (self.path / "eval"
                / f"{data_config.scene}-{data_config.protocol}-{split}-e{epoch}.json")

    def read_evaluation(self, data_config: DataConfig, split: str, epoch: int) -> dict | None:
        path = self.evaluation_path(data_config, split, epoch)
        return json.loads(path.read_text()) if path.exists() else None

    def check_writable(self) -> None:
        """Refuse early where results could not be written (a read-only work directory)."""
        folder = self.path / "eval"
        while not folder.exists() and folder != folder.parent:     # what would be created
            folder = folder.parent
        if not os.access(folder, os.W_OK):
            raise RunError(f"cannot write in {folder}; evaluate a writable copy, or print the "
                           "result with --json")

    def write_evaluation(self, data_config: DataConfig, split: str, epoch: int, result: dict,
                         markdown: str) -> Path:
        """Write an evaluation's JSON and markdown (process 0); returns the JSON path."""
        path = self.evaluation_path(data_config, split, epoch)
        if self.writes:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(result, indent=2) + "\n")
            path.with_suffix(".md").write_text(markdown)
        return path

    def results_path(self, suffix: str) -> Path:
        """A sweep's results.<suffix>."""
        return self.path / f"results.{suffix}"


@dataclasses.dataclass(frozen=True)
class Run:
    """A trained model read back: its configs, parameters and where it came from.

    name: how it was named (a work directory, `DIR:MEMBER` or `pretrained:NAME`);
    workdir: its work directory, None for a shipped model.
    """

    name: str
    model_config: ModelConfig
    data_config: DataConfig
    train_config: TrainConfig
    params: Any
    epoch: int
    workdir: WorkDir | None

    @property
    def figures(self) -> Path:
        """Where its figures go: its work directory's figures/, or runs/figures/<name>."""
        if self.workdir is not None:
            return self.workdir.figures
        return RUNS / "figures" / self.name.replace(":", "-").replace("/", "-")


def load_model(spec: str | Path, epoch: int | None = None) -> Run:
    """A work directory (or one of its checkpoints), `SWEEP_DIR:MEMBER` or `pretrained:NAME`."""
    spec = str(spec)
    where, _, member = spec.partition(":")
    if where == "pretrained":
        return load_pretrained_run(member)
    if member:
        return load_member(where, member, epoch)
    return load_run(spec, epoch)


def load_run(path: str | Path, epoch: int | None = None) -> Run:
    """Read a work directory, its checkpoints/ folder or one checkpoints/<epoch>."""
    path = Path(path)
    if path.name.isdigit() and path.parent.name == "checkpoints":
        epoch = int(path.name) if epoch is None else epoch
        path = path.parent.parent
    elif path.name == "checkpoints":
        path = path.parent
    workdir = WorkDir(path)
    checkpointer = workdir.checkpointer(create=False)
    try:
        config = checkpointer.read_config(epoch)
        if "members" in config:
            names = ", ".join(Member(**m).name for m in config["members"])
            raise RunError(f"{path} is a sweep: name one member as {path}:MEMBER ({names})")
        model_config = ModelConfig(**config["model"])
        state, _, _, epoch = checkpointer.restore(abstract_train_state(model_config), epoch,
                                                  fall_back=epoch is None)
    finally:
        checkpointer.close()
    return Run(name=str(path), model_config=model_config,
               data_config=DataConfig(**config["data"]),
               train_config=TrainConfig(**config["train"]), params=state.params, epoch=epoch,
               workdir=workdir)


def load_member(path: str | Path, name: str, epoch: int | None = None) -> Run:
    """One member of a sweep's stacked checkpoint as a single run (e.g. to simulate it).

    name: a member name such as 'n4-partial-seed1000'. The run's config has the member's n
    and detection switch, and the sweep's head slots.
    """
    workdir = WorkDir(path)
    checkpointer = workdir.checkpointer(create=False)
    try:
        config = checkpointer.read_config(epoch)
        if "members" not in config:
            raise RunError(f"{path} holds a single run, not a sweep")
        members = [Member(**m) for m in config["members"]]
        names = [m.name for m in members]
        if name not in names:
            raise RunError(f"{path} has no member {name!r}; it has {', '.join(names)}")
        model_config = ModelConfig(**config["model"])
        like = stacked_shape(abstract_train_state(model_config), len(members))
        state, _, _, epoch = checkpointer.restore(like, epoch, fall_back=epoch is None)
    finally:
        checkpointer.close()
    member = members[names.index(name)]
    train_config = TrainConfig(**{**config["train"], "seed": member.seed,
                                  "fully_detected_only": member.fully_detected_only})
    return Run(name=f"{path}:{name}", model_config=member_config(model_config, member),
               data_config=DataConfig(**config["data"]), train_config=train_config,
               params=unstack(state.params, names.index(name)), epoch=epoch, workdir=workdir)


def load_pretrained_run(name: str) -> Run:
    """A shipped model (`gst_jax/pretrained/<name>`) as a run without a work directory."""
    try:
        meta = pretrained.load_meta(name)
    except KeyError as error:
        raise RunError(error.args[0]) from None
    model_config, params = pretrained.load_pretrained(name)
    return Run(name=f"pretrained:{name}", model_config=model_config,
               data_config=DataConfig(**meta["data"]), train_config=TrainConfig(**meta["train"]),
               params=params, epoch=meta["epoch"], workdir=None)
