"""XLA:CPU's YNNPACK fusions, setting by setting: the planner path and a training epoch.

    python benchmarks/bench_ynnpack.py                          # every setting, this checkout
    python benchmarks/bench_ynnpack.py --against 7639df8        # and another commit's code
    python benchmarks/bench_ynnpack.py --check                  # exit 1 if the default is slow

Each setting runs in a process of its own (XLA reads the flag when its CPU backend starts):
`default` is what importing gst_jax chooses (docs/benchmarks.md, "Conditions": XLA's own
choice in a process of one device), the others give `--xla_cpu_experimental_ynn_fusion_type`
explicitly (`dot,eltwise,reduce`, which is not XLA's default; products only; `none`, no
YNNPACK fusion). Measured in each:
- drop-in: CrowdNav++'s predictor (`gst_jax.crowdnav`, the `crowdnav_parity` fixture's
  seed-1000 weights), 16 environments x 20 humans, mean mode, numpy in and out;
- predict: the paper's model (`pretrained:zara1_d`), K = 20 samples of one scene of 16 people;
- stream step: one robot's `gst_jax.stream` step over 50 people with DtACI regions
  (`pretrained:crowdnav_sj`, as bench_stream.py);
- training: `python -m gst_jax.train --scene eth --epochs 3 --max-train-windows 128`, the
  median of epochs 2-3 (compiled in epoch 1), tcmalloc preloaded where it is installed.
Each call is timed in `--rounds` rounds of `--calls` calls after compiling: the minimum and
the median of the round medians, in each of `--passes` processes per setting (interleaved across
the settings); the table gives each setting's fastest pass. `--check` compares the default with
the fastest setting on the drop-in and the stream step and fails when the default is slower by
more than `--margin` (the run-to-run noise of a quiet machine).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FLAG = "--xla_cpu_experimental_ynn_fusion_type"
SETTINGS = {"default": None, "dot,eltwise,reduce": "dot,eltwise,reduce", "dot": "dot",
            "none": ""}
CASES = ("drop-in", "predict", "stream step")
TCMALLOC = "/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4"


def timed(call, rounds: int, calls: int) -> tuple[float, float]:
    """(min, median) over rounds of each round's median seconds per call, after one call."""
    call()
    medians = []
    for _ in range(rounds):
        times = []
        for _ in range(calls):
            start = time.perf_counter()
            call()
            times.append(time.perf_counter() - start)
        medians.append(statistics.median(times))
    return min(medians), statistics.median(medians)


def worker(rounds: int, calls: int) -> dict:
    """The three planner-path calls in this process (its XLA_FLAGS as given)."""
    import jax
    import numpy as np

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import gst_jax
    from bench_crowdnav import inputs, ours
    from gst_jax.runs import load_model

    out = {}
    predictor = ours()
    traj, mask = inputs(16)
    out["drop-in"] = timed(lambda: [np.asarray(a) for a in predictor(traj, mask)], rounds, calls)

    run = load_model("pretrained:zara1_d")
    predict = gst_jax.make_predict(run.model_config, num_samples=20)
    rng = np.random.default_rng(0)
    observed = np.cumsum(rng.normal(0.0, 0.3, (1, 8, 16, 2)), axis=1)
    batch = gst_jax.make_batch(observed, grid=run.model_config.grid)
    key = jax.random.key(0)
    out["predict"] = timed(lambda: predict(run.params, key, batch).positions.block_until_ready(),
                           rounds, calls)

    try:
        from bench_stream import time_case
    except ImportError:                   # code from before gst_jax.stream
        out["stream step"] = None
    else:
        stream = time_case(load_model("pretrained:crowdnav_sj"), 1, 50, 0, rounds * calls)
        out["stream step"] = (stream["min_ms"] / 1e3, stream["median_ms"] / 1e3)
    out["xla_flags"] = os.environ.get("XLA_FLAGS", "")
    return out


def environment(setting: str | None, tree: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    flags = " ".join(f for f in env.get("XLA_FLAGS", "").split() if FLAG not in f)
    env["XLA_FLAGS"] = flags if setting is None else f"{flags} {FLAG}={setting}".strip()
    if Path(TCMALLOC).exists():
        env["LD_PRELOAD"] = TCMALLOC
    return env


def measure(setting: str | None, tree: Path, rounds: int, calls: int, train: bool) -> dict:
    env = environment(setting, tree)
    script = (f"import json, sys; sys.path.insert(0, {str(ROOT / 'benchmarks')!r}); "
              f"from bench_ynnpack import worker; print(json.dumps(worker({rounds}, {calls})))")
    result = subprocess.run([sys.executable, "-c", script], env=env, cwd=tree,
                            capture_output=True, text=True)
    if result.returncode:
        raise SystemExit(f"setting {setting!r} in {tree}: exit {result.returncode}\n"
                         f"{result.stderr[-2000:]}")
    out = json.loads(result.stdout.strip().splitlines()[-1])
    if train:
        out["training epoch"] = training_epoch(env, tree)
    return out


def training_epoch(env: dict, tree: Path) -> tuple[float, float]:
    with tempfile.TemporaryDirectory() as workdir:
        subprocess.run([sys.executable, "-m", "gst_jax.train", "--scene", "eth", "--epochs", "3",
                        "--max-train-windows", "128", "--checkpoint-every", "100",
                        "--workdir", workdir], env=env, cwd=tree, check=True,
                       capture_output=True)
        lines = (Path(workdir) / "timings.jsonl")
        if not lines.exists():            # code from before timings.jsonl
            lines = Path(workdir) / "metrics.jsonl"
        times = [json.loads(line)["epoch_time_s"] for line in lines.read_text().splitlines()][1:]
    return min(times), statistics.median(times)


def export_tree(commit: str) -> Path:
    """A copy of `commit`'s package and data, outside the checkout."""
    folder = Path(tempfile.mkdtemp(prefix=f"ynnpack-{commit}-"))
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "gst_jax", "data"],
                             capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--settings", nargs="*", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--against", default=None, metavar="COMMIT",
                        help="also time COMMIT's code with its own default (no flag given)")
    parser.add_argument("--passes", type=int, default=3,
                        help="processes per setting, interleaved across the settings, so that "
                             "a slow spell of the machine falls on all of them (default: 3)")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--calls", type=int, default=30)
    parser.add_argument("--no-train", action="store_true", help="skip the training epochs")
    parser.add_argument("--check", action="store_true",
                        help="exit 1 if the default is slower than the fastest setting")
    parser.add_argument("--margin", type=float, default=0.10,
                        help="--check's allowance over the fastest (default: 0.10)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = parser.parse_args()

    rows = []
    runs = [(name, SETTINGS[name], ROOT, "this checkout") for name in args.settings]
    if args.against:
        runs.append(("default", None, export_tree(args.against), args.against))
    passes = {}
    for number in range(args.passes):
        for name, setting, tree, code in runs:
            print(f"timing {name} ({code}), pass {number + 1} ...", file=sys.stderr, flush=True)
            passes.setdefault((name, code), []).append(
                measure(setting, tree, args.rounds, args.calls, not args.no_train))
    for (name, code), measured in passes.items():
        # Per case: the fastest pass's (min, median), the pass least disturbed by the machine.
        row = {"setting": name, "code": code}
        for case in measured[0]:
            if case != "xla_flags":
                values = [m[case] for m in measured if m[case] is not None]
                row[case] = min(values, key=lambda v: v[1]) if values else None
        rows.append(row)
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        cases = CASES + (() if args.no_train else ("training epoch",))
        print("| code | setting | " + " | ".join(f"{c} (min / median)" for c in cases) + " |")
        print("|---|---|" + "---|" * len(cases))
        for row in rows:
            cells = ["-" if row[c] is None else
                     f"{row[c][0]:.2f} / {row[c][1]:.2f} s" if c == "training epoch" else
                     f"{1e3 * row[c][0]:.2f} / {1e3 * row[c][1]:.2f} ms" for c in cases]
            print(f"| {row['code']} | {row['setting']} | " + " | ".join(cells) + " |")
    if args.check:
        ours = [r for r in rows if r["code"] == "this checkout"]
        default = next(r for r in ours if r["setting"] == "default")
        slow = []
        for case in ("drop-in", "stream step"):
            best = min(r[case][1] for r in ours)
            if default[case][1] > best * (1 + args.margin):
                slow.append(f"{case}: default {1e3 * default[case][1]:.2f} ms, fastest "
                            f"{1e3 * best:.2f} ms")
        print("check: " + ("; ".join(slow) if slow else
                           f"the default is within {args.margin:.0%} of the fastest setting"))
        raise SystemExit(1 if slow else 0)


if __name__ == "__main__":
    main()
