"""Work directories, the only module that knows their layout, and how a model is named.

    <workdir>/config.json                 the run's configuration (model, data, train[, members])
    <workdir>/checkpoints/<epoch>/        orbax: the training state and the config
    <workdir>/metrics.jsonl               one JSON line per epoch
    <workdir>/summary.json                the training's summary, once it has finished
    <workdir>/eval/<scene>-<protocol>-<split>-e<epoch>.json, .md    evaluations
    <workdir>/figures/                    figures of `python -m gst_jax.plot`
    <workdir>/results.json, .csv, .md     a sweep's evaluation of its members

A model is named by a work directory (or one of its `checkpoints/<epoch>`), by
`SWEEP_DIR:MEMBER` for one member of a sweep, or by `pretrained:NAME` for a shipped model.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Sequence

import jax
import orbax.checkpoint as ocp

from gst_jax import pretrained
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.training.members import Member, member_config, stacked_shape, unstack
from gst_jax.training.state import abstract_train_state


# Where commands put work directories unless told (--workdir), relative to the current folder.
RUNS = Path("runs")


class RunError(Exception):
    """A work directory or model name that cannot be used; the message says why."""


class Checkpointer:
    """Saves `{state, config}` under `<workdir>/checkpoints/<epoch>`; restores the latest.

    Saving is synchronous: a checkpoint that `save` returned from is complete on disk, so a
    process killed at any later moment resumes from it.
    """

    def __init__(self, directory: Path, max_to_keep: int = 3, *, create: bool = True):
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=create,
                                               enable_async_checkpointing=False)
        self._manager = ocp.CheckpointManager(directory.absolute(), options=options)

    @property
    def latest_epoch(self) -> int | None:
        return self._manager.latest_step()

    def save(self, epoch: int, state: Any, config: dict) -> None:
        self._manager.save(epoch, args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(config)))
        self._manager.wait_until_finished()

    def restore(self, like_state: Any, epoch: int | None = None) -> tuple[Any, dict, int]:
        """Restore `(state, config, epoch)`; `like_state` (arrays or their abstract shapes)
        gives the tree structure and dtypes."""
        epoch = self._epoch(epoch)
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like_state)
        restored = self._manager.restore(epoch, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract), config=ocp.args.JsonRestore()))
        return restored.state, restored.config, epoch

    def read_config(self, epoch: int | None = None) -> dict:
        """The JSON config stored with a checkpoint, without touching the arrays."""
        return self._manager.restore(self._epoch(epoch), args=ocp.args.Composite(
            config=ocp.args.JsonRestore())).config

    def _epoch(self, epoch: int | None) -> int:
        epoch = self.latest_epoch if epoch is None else epoch
        if epoch is None:
            raise RunError(f"no checkpoint under {self._manager.directory}")
        return epoch

    def close(self) -> None:
        self._manager.close()


def run_config(model_config: ModelConfig, data_config: DataConfig, train_config: TrainConfig,
               members: Sequence[Member] | None = None) -> dict:
    """The JSON description of a run (or sweep), stored in its work dir and checkpoints."""
    config = {"model": dataclasses.asdict(model_config), "data": dataclasses.asdict(data_config),
              "train": dataclasses.asdict(train_config)}
    if members is not None:
        config["members"] = [dataclasses.asdict(m) for m in members]
    return config


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
    if train_config.fully_detected_only:
        parts.append("fd")
    parts += [f"e{train_config.epochs}", f"seed{train_config.seed}"]
    return "-".join(parts)


def sweep_name(data_config: DataConfig, train_config: TrainConfig) -> str:
    """The default work directory name of a sweep."""
    return f"sweep-{data_config.scene}-e{train_config.epochs}"


class WorkDir:
    """The files of one work directory (see the module docstring for the layout)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"WorkDir({str(self.path)!r})"

    @property
    def metrics_path(self) -> Path:
        return self.path / "metrics.jsonl"

    @property
    def figures(self) -> Path:
        return self.path / "figures"

    def prepare(self, config: dict) -> None:
        """Create the work dir, or check that an existing one belongs to the same run."""
        config_path = self.path / "config.json"
        if config_path.exists():
            if json.loads(config_path.read_text()) != config:
                raise RunError(f"{self.path} holds a run with a different configuration "
                               f"({config_path}); choose another --workdir or delete it")
            return
        self.path.mkdir(parents=True, exist_ok=True)
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
        with self.metrics_path.open("a") as f:
            f.write(json.dumps(record) + "\n")

    def truncate_metrics(self, last_epoch: int) -> None:
        """Drop the records of epochs after `last_epoch` (what a killed run wrote after the
        checkpoint it resumes from)."""
        kept = [r for r in self.read_metrics() if r.get("epoch", 0) <= last_epoch]
        self.metrics_path.write_text("".join(json.dumps(r) + "\n" for r in kept))

    def training_time_s(self) -> float:
        """Sum of the epoch times: the training's wall time across resumes."""
        return sum(r.get("epoch_time_s", 0.0) for r in self.read_metrics())

    def write_summary(self, summary: dict) -> None:
        (self.path / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")

    def evaluation_path(self, data_config: DataConfig, split: str, epoch: int) -> Path:
        """eval/<scene>-<protocol>-<split>-e<epoch>.json (the .md beside it)."""
        return (self.path / "eval"
                / f"{data_config.scene}-{data_config.protocol}-{split}-e{epoch}.json")

    def read_evaluation(self, data_config: DataConfig, split: str, epoch: int) -> dict | None:
        path = self.evaluation_path(data_config, split, epoch)
        return json.loads(path.read_text()) if path.exists() else None

    def write_evaluation(self, data_config: DataConfig, split: str, epoch: int, result: dict,
                         markdown: str) -> Path:
        """Write an evaluation's JSON and markdown; returns the JSON path."""
        path = self.evaluation_path(data_config, split, epoch)
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
        state, _, epoch = checkpointer.restore(abstract_train_state(model_config), epoch)
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
        state, _, epoch = checkpointer.restore(like, epoch)
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
