"""A trained model by name: a work directory (or one of its `checkpoints/<epoch>`),
`SWEEP_DIR:MEMBER` for one member of a sweep, `pretrained:NAME` for a shipped model, or a
weights folder (model.safetensors and config.json, `gst_jax.model.weights`) for one exported."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from gst_jax import pretrained
from gst_jax.config import DataConfig, Member, ModelConfig, TrainConfig
from gst_jax.errors import RunError
from gst_jax.io.workdir import RUNS, WorkDir
from gst_jax.model import Params, weights
from gst_jax.training.members import member_config, stacked_shape, unstack
from gst_jax.training.state import abstract_train_state


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
    params: Params
    epoch: int
    workdir: WorkDir | None

    def with_candidates(self, count: int | None) -> "Run":
        """The same parameters predicting with a candidate neighbourhood of `count` (0: the
        exact model; docs/MODEL.md 2.4); None: as it is."""
        if count is None:
            return self
        return dataclasses.replace(self, model_config=dataclasses.replace(
            self.model_config, candidates=count))

    @property
    def figures(self) -> Path:
        """Where its figures go: its work directory's figures/, or runs/figures/<name>."""
        if self.workdir is not None:
            return self.workdir.figures
        return RUNS / "figures" / self.name.replace(":", "-").replace("/", "-")


def load_model(spec: str | Path, epoch: int | None = None) -> Run:
    """A work directory (or one of its checkpoints), `SWEEP_DIR:MEMBER`, `pretrained:NAME` or
    a weights folder (`python -m gst_jax.pretrained export MODEL --out DIR`: DIR, or
    DIR/model.safetensors). A path that exists is a path, ':' in its name or not; else the
    member follows the last ':' (so a sweep directory may have ':' in its name too)."""
    spec = str(spec)
    if spec.startswith(weights.PRETRAINED):
        return load_pretrained_run(spec.removeprefix(weights.PRETRAINED), epoch)
    if weights.is_weights(spec):
        return load_weights_run(spec, epoch)
    where, colon, member = spec.rpartition(":")
    if colon and not Path(spec).exists() and where:
        return load_member(where, member, epoch)
    return load_run(spec, epoch)


def load_run(path: str | Path, epoch: int | None = None) -> Run:
    """Read a work directory, its checkpoints/ folder or one checkpoints/<epoch>. By default
    its newest checkpoint, or, for a fine-tuning, the epoch it selected (its selected/)."""
    path = Path(path)
    if path.name.isdigit() and path.parent.name == "checkpoints":
        epoch = int(path.name) if epoch is None else epoch
        path = path.parent.parent
    elif path.name == "checkpoints":
        path = path.parent
    workdir = WorkDir(path)
    selected = workdir.selected_checkpointer(create=False) if epoch is None else None
    checkpointer = selected or workdir.checkpointer(create=False)
    try:
        config = checkpointer.read_config(epoch)
        if "members" in config:
            names = ", ".join(Member(**m).name for m in config["members"])
            raise RunError(f"{path} is a sweep: name one member as {path}:MEMBER ({names})")
        model_config = ModelConfig.from_dict(config["model"])
        restored = checkpointer.restore(abstract_train_state(model_config), epoch,
                                        fall_back=epoch is None)
    finally:
        checkpointer.close()
    return Run(name=str(path), model_config=model_config,
               data_config=stored_data_config(config, path),
               train_config=TrainConfig.from_dict(config["train"]), params=restored.state.params,
               epoch=restored.epoch,
               workdir=workdir)


def stored_data_config(config: dict, path: str | Path) -> DataConfig:
    """A checkpoint's data config, checked (its scene a name, not a path): RunError naming
    the run otherwise."""
    try:
        return DataConfig.from_dict(config["data"])
    except (TypeError, ValueError) as error:
        raise RunError(f"{path}: its stored data config: {error}") from None


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
        model_config = ModelConfig.from_dict(config["model"])
        like = stacked_shape(abstract_train_state(model_config), len(members))
        restored = checkpointer.restore(like, epoch, fall_back=epoch is None)
    finally:
        checkpointer.close()
    member = members[names.index(name)]
    train_config = TrainConfig.from_dict({**config["train"], "seed": member.seed,
                                          "fully_detected_only": member.fully_detected_only})
    return Run(name=f"{path}:{name}", model_config=member_config(model_config, member),
               data_config=stored_data_config(config, path), train_config=train_config,
               params=unstack(restored.state.params, names.index(name)), epoch=restored.epoch,
               workdir=workdir)


def load_weights_run(path: str | Path, epoch: int | None = None) -> Run:
    """A weights folder (model.safetensors and config.json, `gst_jax.model.weights`), or its
    model.safetensors, as a run without a work directory; checked: its checksum, and its
    parameters against its model config. It holds one epoch: another is refused."""
    loaded = weights.load(path)
    config = loaded.config
    if epoch is not None and epoch != config.get("epoch"):
        raise RunError(f"{loaded.folder} holds the parameters of epoch {config.get('epoch')} "
                       f"only, not of epoch {epoch}")
    try:
        data_config = DataConfig.from_dict(config.get("data", {}))
        train_config = TrainConfig.from_dict(config.get("train", {}))
    except (TypeError, ValueError) as error:
        raise RunError(f"{loaded.folder / weights.CONFIG_FILE}: {error}") from None
    return Run(name=str(path), model_config=loaded.model_config, data_config=data_config,
               train_config=train_config, params=loaded.params, epoch=config.get("epoch", 0),
               workdir=None)


def load_pretrained_run(name: str, epoch: int | None = None) -> Run:
    """A shipped model (`gst_jax/pretrained/<name>`) as a run without a work directory."""
    run = load_weights_run(pretrained.folder(name), epoch)
    return dataclasses.replace(run, name=f"pretrained:{name}")
