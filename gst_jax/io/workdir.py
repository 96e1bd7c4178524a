"""Work directories, the only module that knows their layout, and how a run is named.

    <workdir>/config.json                 the run's configuration (model, data, train[, members])
    <workdir>/checkpoints/<epoch>/        orbax: the training state and the config
    <workdir>/interrupted/<epoch>/        the same, saved inside an epoch by a stop signal
                                          (with where in the epoch), until a later save; gone
                                          once the training has finished
    <workdir>/selected/<epoch>/           a fine-tuning's model: the epoch (0: the model it
                                          started from) of the best validation AOE
    <workdir>/lock                        held by the process that trains in it, while it does
    <workdir>/metrics.jsonl               one JSON line per epoch: what the training computed
                                          (loss, schedule, validation, the code that trained it);
                                          the same command on the same machine writes it anew
                                          byte for byte
    <workdir>/timings.jsonl               one JSON line per epoch: how long it took (TIMINGS)
    <workdir>/summary.json                the training's summary, once it has finished
    <workdir>/eval/<scene>-<protocol>-<split>-e<epoch>.json, .md    evaluations
    <workdir>/figures/                    figures of `python -m gst_jax.plot`
    <workdir>/results.json, .csv, .md     a sweep's evaluation of its members
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import functools
import json
import os
import socket
import subprocess
import time
import warnings
from pathlib import Path
from typing import Any, Iterator, Literal, Sequence, overload

import jax

from gst_jax.config import DataConfig, Member, ModelConfig, TimeGrid, TrainConfig
from gst_jax.errors import RunError
from gst_jax.io.checkpoints import Checkpointer, write_atomically
from gst_jax.model.heads import head

__all__ = ["WorkDir", "code_version", "run_config", "run_name", "same_run", "sweep_name",
           "write_text"]

# Where commands put work directories unless told (--workdir), relative to the current folder.
RUNS = Path("runs")
# The fields of an epoch's record that measure the machine, not the training: kept out of
# metrics.jsonl in timings.jsonl, so that two runs of one command leave identical metrics.
TIMINGS = ("epoch_time_s", "scenes_per_s", "compiles", "compile_time_s", "finished_at")
# K of the paper's protocol (evaluate's --samples default): its records keep the names they
# had; an evaluation with another K is named for it, so that a quick look with --samples 2
# does not replace the K = 20 record.
EVALUATION_SAMPLES = 20


@functools.cache
def code_version() -> str:
    """The git commit of this gst_jax checkout ('+dirty' when gst_jax/ has uncommitted
    changes), recorded with every epoch so that a result names the code that trained it;
    outside a git checkout, $GST_JAX_CODE_VERSION where set (a tree copied to a cluster can
    name the commit it was copied from), else 'gst_jax <version>' (a bare tree says so)."""
    root = Path(__file__).resolve().parents[2]           # the checkout holding gst_jax/
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


def run_config(model_config: ModelConfig, data_config: DataConfig, train_config: TrainConfig,
               members: Sequence[Member] | None = None) -> dict:
    """The JSON description of a run (or sweep), stored in its work dir and checkpoints."""
    config: dict[str, Any] = {"model": dataclasses.asdict(model_config),
                              "data": dataclasses.asdict(data_config),
                              "train": dataclasses.asdict(train_config)}
    if members is not None:
        config["members"] = [dataclasses.asdict(m) for m in members]
    return config


def same_run(config: dict, other: dict) -> bool:
    """Whether two run configs train the same thing: equal configs once read back
    (`from_dict`: missing fields take their defaults, retired ones are dropped). The checkpoint
    cadence says only how often the run is saved, so a resumed run may change it (e.g. to save
    every epoch of a long run that has to be continued over several sittings)."""
    def identity(c: dict) -> dict:
        train = dataclasses.asdict(TrainConfig.from_dict(c["train"]))
        del train["checkpoint_every"]
        return {**c, "model": dataclasses.asdict(ModelConfig.from_dict(c["model"])),
                "data": dataclasses.asdict(DataConfig.from_dict(c["data"])), "train": train}
    return identity(config) == identity(other)


def run_name(data_config: DataConfig, model_config: ModelConfig,
             train_config: TrainConfig) -> str:
    """A work directory name that identifies a run, so the same command finds it to resume."""
    parts = [data_config.scene, data_config.protocol,
             head(model_config.output).letter,
             f"n{model_config.num_edge_heads}"]
    if not model_config.ghost:
        parts.append("noghost")
    if model_config.temporal != ModelConfig.temporal:
        parts.append(model_config.temporal)
    if model_config.node_dim != ModelConfig.node_dim:
        parts.append(f"d{model_config.node_dim}")
    if model_config.encoder_layers != ModelConfig.encoder_layers:
        parts.append(f"layers{model_config.encoder_layers}")
    if model_config.lstm_hidden != ModelConfig.lstm_hidden:
        parts.append(f"lstm{model_config.lstm_hidden}")
    if model_config.attention != ModelConfig.attention:
        parts.append(model_config.attention)
    if model_config.grid != TimeGrid():
        grid = model_config.grid
        parts.append(f"{grid.obs_len}+{grid.pred_len}x{grid.step_s:g}s")
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


def write_text(path: Path, text: str, mode: str = "w") -> None:
    """Write (or with mode "a" append) `text`; a failure names the file (Python's write()
    errors do not), which the commands print as one line."""
    try:
        with open(path, mode) as f:
            f.write(text)
    except OSError as error:
        raise OSError(error.errno, error.strerror, str(path)) from None


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
    def timings_path(self) -> Path:
        return self.path / "timings.jsonl"

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
                write_text(config_path, json.dumps(config, indent=2) + "\n")
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
            write_text(config_path, json.dumps(config, indent=2) + "\n")

    def checkpointer(self, *, create: bool = True) -> Checkpointer:
        """The run's checkpoints; `create=False` reads only and fails without creating
        anything where there are none."""
        directory = self.path / "checkpoints"
        if not create and not directory.is_dir():
            raise RunError(f"no checkpoint in {self.path} (expected {directory}/<epoch>)")
        return Checkpointer(directory, create=create)

    @overload
    def selected_checkpointer(self, *, create: Literal[True] = True) -> Checkpointer: ...
    @overload
    def selected_checkpointer(self, *, create: bool) -> Checkpointer | None: ...
    def selected_checkpointer(self, *, create: bool = True) -> Checkpointer | None:
        """The epoch a fine-tuning selected (`gst_jax.training.selection`); with `create=False`,
        None where there is none."""
        directory = self.path / "selected"
        if not create and not directory.is_dir():
            return None
        return Checkpointer(directory, max_to_keep=1, create=create)

    def interrupted_checkpointer(self) -> Checkpointer:
        """The checkpoint a stop signal saved inside an epoch (one at most)."""
        return Checkpointer(self.path / "interrupted", max_to_keep=1)

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Hold the work directory for this process (training): a second process training
        into it is refused, naming the holder. The lock is the kernel's (`flock`), so that of
        a killed process is gone with it; the `lock` file is removed when the holder is done.
        With several processes, process 0's."""
        if not self.writes:
            yield
            return
        self.path.mkdir(parents=True, exist_ok=True)
        path = self.path / "lock"
        while True:
            f = open(path, "a+")
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                f.seek(0)
                holder = f.read().strip() or "another process"
                f.close()
                raise RunError(f"{self.path} is in use by {holder}; wait for it to finish, or "
                               "stop it, before training there") from None
            # Locked, but perhaps a file its holder removed meanwhile: lock the one there now.
            if path.exists() and os.stat(path).st_ino == os.fstat(f.fileno()).st_ino:
                break
            f.close()
        with f:
            f.seek(0)
            f.truncate()
            f.write(f"process {os.getpid()} on {socket.gethostname()} since "
                    f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n")
            f.flush()
            try:
                yield
            finally:
                path.unlink(missing_ok=True)        # before the lock goes, so none is lost

    def tidy(self) -> None:
        """After a finished training: remove the empty `interrupted/` (its checkpoint is
        discarded once a later one is saved)."""
        folder = self.path / "interrupted"
        if self.writes and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()

    def read_summary(self) -> dict | None:
        """summary.json of a finished training, or None."""
        path = self.path / "summary.json"
        return json.loads(path.read_text()) if path.exists() else None

    def read_metrics(self) -> list[dict]:
        """The per-epoch records, in order ([] before the first epoch): each line of
        metrics.jsonl with the same epoch's timings.jsonl line merged in (work directories
        written before the split hold both in metrics.jsonl). A line cut short (a full disk)
        is skipped with a warning."""
        timings = {record.get("epoch"): record for record in _read_lines(self.timings_path)}
        return [{**record, **{k: v for k, v in timings.get(record.get("epoch"), {}).items()
                              if k != "epoch"}}
                for record in _read_lines(self.metrics_path)]

    def append_metrics(self, record: dict) -> None:
        if not self.writes:
            return
        computed, timing = _split_timings(record)
        write_text(self.metrics_path, json.dumps(computed) + "\n", mode="a")
        write_text(self.timings_path, json.dumps(timing) + "\n", mode="a")

    def write_metrics(self, records: list[dict]) -> None:
        """Replace metrics.jsonl and timings.jsonl by `records` (a resume: those of its
        checkpoint, which drop what a killed run wrote after it and restore what it did not
        get to write)."""
        if self.writes:
            split = [_split_timings(r) for r in records]
            write_atomically(self.metrics_path, "".join(json.dumps(c) + "\n" for c, _ in split))
            write_atomically(self.timings_path, "".join(json.dumps(t) + "\n" for _, t in split))

    def code_versions(self) -> list[str]:
        """The code versions that trained the run's epochs, in order of first use."""
        return list(dict.fromkeys(r["code"] for r in self.read_metrics() if "code" in r))

    def training_time_s(self) -> float:
        """Sum of the epoch times: the training's wall time across resumes."""
        return sum(r.get("epoch_time_s", 0.0) for r in self.read_metrics())

    def write_summary(self, summary: dict) -> None:
        if self.writes:
            write_text(self.path / "summary.json", json.dumps(summary, indent=2) + "\n")

    def evaluation_path(self, data_config: DataConfig, split: str, epoch: int,
                        num_samples: int = EVALUATION_SAMPLES) -> Path:
        """eval/<scene>-<protocol>-<split>-e<epoch>.json (the .md beside it), with -k<K>
        before .json where K is not EVALUATION_SAMPLES; never outside eval/, whatever a
        config names (`DataConfig` keeps scenes to names)."""
        samples = "" if num_samples == EVALUATION_SAMPLES else f"-k{num_samples}"
        path = (self.path / "eval" / f"{data_config.scene}-{data_config.protocol}-{split}"
                                     f"-e{epoch}{samples}.json")
        if path.parent != self.path / "eval":
            raise RunError(f"{data_config.scene!r} is not a scene's name: its evaluation "
                           f"would be written outside {self.path / 'eval'}")
        return path

    def read_evaluation(self, data_config: DataConfig, split: str, epoch: int,
                        num_samples: int = EVALUATION_SAMPLES) -> dict | None:
        path = self.evaluation_path(data_config, split, epoch, num_samples)
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
        """Write an evaluation (its JSON and markdown, process 0), named by its K
        (`result["samples"]`); returns the JSON path."""
        path = self.evaluation_path(data_config, split, epoch,
                                    result.get("samples", EVALUATION_SAMPLES))
        if self.writes:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_text(path, json.dumps(result, indent=2) + "\n")
            write_text(path.with_suffix(".md"), markdown)
        return path

    def results_path(self, suffix: str) -> Path:
        """A sweep's results.<suffix>."""
        return self.path / f"results.{suffix}"


def _split_timings(record: dict) -> tuple[dict, dict]:
    """An epoch's record -> (what metrics.jsonl keeps, its timings.jsonl line)."""
    computed = {k: v for k, v in record.items() if k not in TIMINGS}
    timing = {"epoch": record.get("epoch"), **{k: record[k] for k in TIMINGS if k in record}}
    return computed, timing


def _read_lines(path: Path) -> list[dict]:
    """The JSON lines of a file ([] where it does not exist), a line cut short skipped with a
    warning."""
    if not path.exists():
        return []
    records = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            warnings.warn(f"{path}:{number}: skipped a line that is not complete JSON (cut "
                          "short by a full disk or a crash?)", stacklevel=3)
    return records
