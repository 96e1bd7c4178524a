"""Exporting a model: as a weights folder anyone can load (`export_weights`: model.safetensors
and config.json, `gst_jax.model.weights`), or as a shipped model of the package (`export`: the
same two files in gst_jax/pretrained/<name>/ with its record, meta.json: its test evaluation
and a fixed-key check).

A model is anything `load_model` names (a work directory, `SWEEP_DIR:MEMBER`,
`pretrained:NAME`, a weights folder) or a CrowdNav++ (`gst_updated`) checkpoint folder, read
without torch (`crowdnav_run`). Its provenance travels with it: the source, the licence, the
licence files beside its weights, CrowdNav++'s args, and the commands that made it.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import jax

from gst_jax import crowdnav, data
from gst_jax.config import CROWD, CROWD_SCENES, DataConfig, ModelConfig, TrainConfig
from gst_jax.errors import RunError
from gst_jax.evaluation import evaluate_params
from gst_jax.io.workdir import run_config
from gst_jax.model import Params, weights
from gst_jax.pretrained import ROOT
from gst_jax.runs import Run, load_model

# The fixed-key check stored with every model: AOE on the first windows of its test split.
CHECK = {"windows": 4, "samples": 2, "seed": 0}
# What a re-export carries over from a weights folder's config.json (or a shipped model's
# record): where the parameters came from, under which licence, and how they were made.
PROVENANCE = ("source", "licence", "crowdnav_args", "commands")
# The name of a licence file beside the weights (LICENSE.<its folder>, so that several
# projects' LICENSE files can sit side by side).
LICENCE_NAMES = ("LICENSE", "LICENCE", "COPYING", "NOTICE")


def check_data_config(meta: dict) -> DataConfig:
    """The data of a shipped model's fixed-key check: its own, or the bundled data it names."""
    return DataConfig.from_dict(meta["check"].get("data", meta["data"]))


def check_aoe(config: ModelConfig, params: Params, data_config: DataConfig) -> float:
    """AOE of the fixed-key check (CHECK) on the first windows of the test split."""
    test_set = data.load_split(data_config, "test", config.grid)
    test_set = test_set.subset(range(min(CHECK["windows"], len(test_set))))
    return evaluate_params(params, jax.random.key(CHECK["seed"]), test_set, config,
                           num_samples=CHECK["samples"], with_kde=False,
                           with_baseline=False)["aoe"]


def is_crowdnav_checkpoint(path: str | Path) -> bool:
    """Whether a path is a CrowdNav++ checkpoint folder (`<run>/sj`: checkpoint/args.pickle)."""
    return (Path(path) / "checkpoint" / "args.pickle").is_file()


def crowdnav_run(path: str | Path) -> Run:
    """A CrowdNav++ (gst_updated) checkpoint folder as a gst_jax model: the ModelConfig of its
    args.pickle (`crowdnav.model_config`), its parameters (`params_from_torch`), its training
    as args.pickle records it. Its data, CrowdNav++'s simulated crowds, are not bundled: the
    scene says so, and a command that needs it asks for --data or --scene."""
    args = crowdnav.checkpoint_args(path)
    predictor = crowdnav.load(path)
    dataset = args.get("dataset", "?")
    data_config = DataConfig(scene=f"crowdnav-{dataset} (CrowdNav++'s simulated crowds, not "
                                   "bundled: give --data or --scene)")
    train_config = TrainConfig(epochs=args["num_epochs"], batch_size=args["batch_size"],
                               learning_rate=args["lr"], tau_start=args["init_temp"],
                               rotate=args.get("rotation_pattern") is not None,
                               seed=args["random_seed"])
    return Run(name=str(path), model_config=predictor.config, data_config=data_config,
               train_config=train_config, params=predictor.params, epoch=args["num_epochs"],
               workdir=None)


def model_run(spec: str | Path) -> Run:
    """A model by any name `load_model` takes, or a CrowdNav++ checkpoint folder."""
    return crowdnav_run(spec) if is_crowdnav_checkpoint(spec) else load_model(spec)


def _provenance(run: Run, spec: str | Path, source: str | None, licence: str | None,
                command: str | None) -> dict:
    """Where the parameters came from: carried over from a weights folder, else the run's."""
    carried = {}
    if weights.is_weights(spec):
        carried = {k: v for k, v in weights.read_config(spec).items() if k in PROVENANCE}
    elif is_crowdnav_checkpoint(spec):
        carried["crowdnav_args"] = crowdnav.checkpoint_args(spec)
    own_source = run.name           # a work directory's absolute, with a sweep member's name
    if run.workdir is not None and run.name.startswith(str(run.workdir.path)):
        own_source = str(run.workdir.path.absolute()) + run.name[len(str(run.workdir.path)):]
    commands = [*carried.pop("commands", []), *([command] if command else [])]
    return {"source": source or carried.pop("source", None) or own_source,
            "licence": licence or carried.pop("licence", None), **carried,
            "commands": commands}


def _licence_files(spec: str | Path, licence_files) -> dict[str, bytes]:
    """{name beside the weights: contents}: those of a weights folder, then those given."""
    found = {}
    if weights.is_weights(spec):
        folder = weights.folder_of(spec)
        found = {p.name: p.read_bytes() for p in sorted(folder.iterdir())
                 if p.name.startswith(LICENCE_NAMES) and p.is_file()}
    for path in map(Path, licence_files):
        name = f"{path.name}.{path.absolute().parent.name}" if "." not in path.name else path.name
        if not path.is_file():
            raise RunError(f"{path}: no such licence file")
        found[name] = path.read_bytes()
    return found


def export_weights(spec: str | Path, out: str | Path, *, source: str | None = None,
                   licence: str | None = None, licence_files=(), command: str | None = None
                   ) -> Path:
    """Write a model as `out/model.safetensors` and `out/config.json` (with its provenance and
    licence files); `load_model(out)` reads it back. Returns `out`."""
    run = model_run(spec)
    record = {"data": dataclasses.asdict(run.data_config),
              "train": dataclasses.asdict(run.train_config), "epoch": run.epoch,
              **_provenance(run, spec, source, licence, command)}
    files = _licence_files(spec, licence_files)
    out = Path(out)
    if out.exists() and not weights.is_weights(out) and any(out.iterdir()):
        raise RunError(f"{out} exists and is not a weights folder: give a new or empty folder")
    weights.save(out, run.model_config, run.params, record)
    for name, contents in files.items():
        (out / name).write_bytes(contents)
    return out


def export(spec: str | Path, name: str, check_data: DataConfig | None = None, *,
           source: str | None = None, licence: str | None = None, licence_files=(),
           command: str | None = None) -> Path:
    """Ship a model as gst_jax/pretrained/<name>: its weights folder and its record, meta.json.
    From a work directory, the record holds its test evaluation (and per scene for the general
    model); from a shipped model, its record carries over. The fixed-key check runs on the
    run's own data, or on `check_data` where that is not bundled (a relative path into the
    bundled data, so that it is found on any machine)."""
    run = model_run(spec)
    previous = {}
    if str(spec).startswith(weights.PRETRAINED):
        previous = json.loads((weights.folder_of(spec) / weights.SHIPPED_RECORD).read_text())
    metrics = per_scene = None
    if run.workdir is not None:
        metrics = run.workdir.read_evaluation(run.data_config, "test", run.epoch)
        if run.data_config.scene == CROWD:    # the general model: its score on every scene
            per_scene = {}
            for scene in CROWD_SCENES:
                config = dataclasses.replace(run.data_config, scene=scene)
                per_scene[scene] = run.workdir.read_evaluation(config, "test", run.epoch)
                if per_scene[scene] is None:
                    raise RunError(f"{run.workdir.path} has no test evaluation on {scene} at "
                                   f"epoch {run.epoch}: run `python experiments/crowd.py "
                                   "--train` first")
    if previous and check_data is None:
        check = previous["check"]
    else:
        check = {**CHECK, "aoe": check_aoe(run.model_config, run.params,
                                           check_data or run.data_config)}
        if check_data is not None:
            check["data"] = dataclasses.asdict(check_data)
    record = {**run_config(run.model_config, run.data_config, run.train_config),
              "epoch": run.epoch, **_provenance(run, spec, source, licence, command)}
    meta = {**previous, **record}
    if run.workdir is not None:
        meta.update({"test_metrics": metrics,
                     **({"test_metrics_per_scene": per_scene} if per_scene else {}),
                     "train_time_s": run.workdir.training_time_s(),
                     "code": run.workdir.code_versions()})
    meta.setdefault("test_metrics", None)
    meta["check"] = check
    files = _licence_files(spec, licence_files)
    folder = ROOT / name
    if folder.exists():
        shutil.rmtree(folder)
    weights.save(folder, run.model_config, run.params,
                 {k: v for k, v in record.items() if k != "model"})
    for file_name, contents in files.items():
        (folder / file_name).write_bytes(contents)
    (folder / weights.SHIPPED_RECORD).write_text(json.dumps(meta, indent=2) + "\n")
    return folder
