"""What the experiment scripts share: training and evaluating a run through the library, and
parking an unfinished run so that another sitting (or machine) continues it.

Run the scripts as `python experiments/<script>.py`: their folder is then on the path, and
`from _common import ...` finds this module (the tests put it there through pytest's
`pythonpath`).

The scripts that tabulate runs write into a folder of their own, runs/<script>/ (or
--workdir), beside the records of the finished evaluations they found (<out>/runs/*.json).
Only `--publish` writes into results/, the published tables and records committed with the
code, and only then do the records there count as finished runs.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import Iterator

import jax

from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.evaluation import evaluate_run, format_markdown
from gst_jax.io.workdir import WorkDir
from gst_jax.runs import load_run
from gst_jax.simulate.crowdnav.environment import CrowdNav, EnvParams, EnvState
from gst_jax.simulate.crowdnav.navigation import max_steps
from gst_jax.simulate.crowdnav.planner import SamplingMPC
from gst_jax.training.loop import fit

# Where unfinished runs are parked (their newest checkpoint, committed so that another sitting
# continues them): one commit per sitting replaces the previous park; results/ holds only
# finished records.
PARKED = Path("parked")
# The published tables and their records, in the checkout beside this folder; written only
# with --publish.
RESULTS = Path(__file__).resolve().parents[1] / "results"


def mpc_states(env: CrowdNav, params: EnvParams, episodes: int, seed: int
               ) -> Iterator[EnvState]:
    """Every state after a step of the first `episodes` episodes (the keys of split(key(seed)))
    with the sampling MPC driving the robot against `env`'s predictions, one step at a time:
    for measuring beside the play what the jitted episodes do not return."""
    planner = SamplingMPC(horizon=env.pred_len, step_s=params.step_s)
    step, reset, plan = jax.jit(env.step_env), jax.jit(env.reset), jax.jit(planner)
    for key in jax.random.split(jax.random.key(seed), episodes):
        reset_key, key = jax.random.split(key)
        obs, state = reset(reset_key, params)
        planner_state = planner.init()
        for _ in range(max_steps(params)):
            key, plan_key, env_key = jax.random.split(key, 3)
            action, planner_state = plan(plan_key, planner_state, obs)
            obs, state, _, done, _ = step(env_key, state, action, params)
            if bool(done):
                break
            yield state


def train(model_config: ModelConfig, data_config: DataConfig, train_config: TrainConfig,
          workdir: Path) -> None:
    """Train (or resume) the run in `workdir`, as `python -m gst_jax.train` does."""
    print(f"training {workdir}", flush=True)
    fit(model_config, data_config, train_config, workdir)


def evaluate(workdir: Path, data_config: DataConfig | None = None) -> dict:
    """Evaluate the run's latest checkpoint on a test split (default: its own) with the
    paper protocol and record it in its eval/, as `python -m gst_jax.evaluate` does."""
    run = load_run(workdir)
    data_config = data_config or run.data_config
    result = evaluate_run(run, data_config, "test")
    WorkDir(workdir).write_evaluation(data_config, "test", run.epoch, result,
                                      format_markdown(result))
    print(f"evaluated {workdir} on {data_config.scene}: AOE {result['aoe']:.3f} "
          f"FOE {result['foe']:.3f}", flush=True)
    return result


def latest_checkpoint(workdir: Path) -> int | None:
    """The epoch of the run's newest checkpoint, or None before the first (reads no array)."""
    folder = Path(workdir) / "checkpoints"
    epochs = [int(p.name) for p in folder.iterdir() if p.name.isdigit()] if folder.is_dir() else []
    return max(epochs, default=None)


def park(workdir: Path, destination: Path) -> int | None:
    """Copy the run's config, newest checkpoint (with its checksums) and evaluations to
    `destination`, a work directory from which training (or, for a finished run, what uses
    its model) continues elsewhere; returns the checkpoint's epoch, or None before the first
    checkpoint."""
    epoch = latest_checkpoint(workdir)
    if epoch is None:
        return None
    source = Path(workdir)
    shutil.rmtree(destination, ignore_errors=True)
    shutil.copytree(source / "checkpoints" / str(epoch), destination / "checkpoints" / str(epoch))
    shutil.copy2(source / "checkpoints" / "checksums.json", destination / "checkpoints")
    shutil.copy2(source / "config.json", destination / "config.json")
    if (source / "eval").is_dir():
        shutil.copytree(source / "eval", destination / "eval")
    return epoch


def add_results_flags(parser: argparse.ArgumentParser, script: str, written: str,
                      runs: bool = True) -> None:
    """--runs, --workdir or --publish, and --json of the scripts that tabulate runs;
    `script`: the default output folder's name, runs/<script>; `written`: what lands there,
    for the help. Read the output folder with `results_folder`."""
    if runs:
        parser.add_argument("--runs", default="runs",
                            help="folder of work directories (default: runs)")
    default = Path("runs") / script
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workdir", type=Path, default=default,
                       help=f"where {written} are written (default: {default})")
    where.add_argument("--publish", action="store_true",
                       help="write into the checkout's results/ instead, replacing the "
                            "published tables" + (" (the finished evaluations recorded there "
                                                  "then count as finished runs)" if runs else ""))
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")


def results_folder(args: argparse.Namespace) -> Path:
    """Where a script parsed with `add_results_flags` writes: results/ with --publish, else
    --workdir."""
    return RESULTS if args.publish else args.workdir
