"""Table I of the paper from existing work directories: our AOE/FOE beside the paper's.

    python experiments/table1.py [--runs runs] [--output deterministic] [--evaluate] [--json]

For each ETH/UCY scene it reads `<runs>/<scene>-paper-<d|p>-n1-e<epochs>-seed<seed>/eval/`
(written by `python -m gst_jax.evaluate`); with `--evaluate` it evaluates runs that have no
evaluation yet. Scenes without a run are listed as missing, never filled in.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from gst_jax.config import ETH_UCY_SCENES

# MODEL.md section 4: the paper's Table I (AOE / FOE in metres, fully detected pedestrians).
PAPER = {
    "deterministic": {"eth": (0.96, 2.09), "hotel": (0.21, 0.38), "univ": (0.50, 1.08),
                      "zara1": (0.40, 0.86), "zara2": (0.32, 0.70)},
    "gaussian": {"eth": (1.10, 2.22), "hotel": (0.22, 0.37), "univ": (0.64, 1.32),
                 "zara1": (0.59, 1.15), "zara2": (0.46, 0.95)},
}


def latest_evaluation(workdir: Path, scene: str) -> dict | None:
    results = sorted((workdir / "eval").glob(f"{scene}-paper-test-e*.json"),
                     key=lambda p: int(p.stem.rsplit("-e", 1)[1]))
    return json.loads(results[-1].read_text()) if results else None


def collect(runs: Path, output: str, epochs: int, seed: int, evaluate: bool) -> list[dict]:
    rows = []
    for scene in ETH_UCY_SCENES:
        workdir = runs / f"{scene}-paper-{output[0]}-n1-e{epochs}-seed{seed}"
        result = latest_evaluation(workdir, scene) if workdir.exists() else None
        if result is None and evaluate and (workdir / "checkpoints").exists():
            subprocess.run([sys.executable, "-m", "gst_jax.evaluate", str(workdir)], check=True)
            result = latest_evaluation(workdir, scene)
        paper_aoe, paper_foe = PAPER[output][scene]
        row = {"scene": scene, "paper_aoe": paper_aoe, "paper_foe": paper_foe,
               "workdir": str(workdir)}
        if result is not None:
            row.update({k: result[k] for k in ("aoe", "aoe_std", "foe", "foe_std", "cv_aoe",
                                               "cv_foe", "epoch", "protocol") if k in result})
        rows.append(row)
    return rows


def markdown(rows: list[dict], output: str) -> str:
    label = "GST (D)" if output == "deterministic" else "GST (P)"
    lines = [f"{label}, paper protocol, n = 1, ghost; AOE / FOE in metres on fully detected "
             "pedestrians; ours = mean ± std over 20 runs (hard samples, tau 0.03).", "",
             "| scene | ours AOE | ours FOE | paper AOE | paper FOE | CV AOE / FOE | epochs |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "aoe" in r:
            cv = f"{r['cv_aoe']:.2f} / {r['cv_foe']:.2f}" if "cv_aoe" in r else "-"
            lines.append(f"| {r['scene']} | {r['aoe']:.2f} ± {r['aoe_std']:.2f} | "
                         f"{r['foe']:.2f} ± {r['foe_std']:.2f} | {r['paper_aoe']:.2f} | "
                         f"{r['paper_foe']:.2f} | {cv} | {r['epoch']} |")
        else:
            lines.append(f"| {r['scene']} | missing | missing | {r['paper_aoe']:.2f} | "
                         f"{r['paper_foe']:.2f} | - | - |")
    done = [r for r in rows if "aoe" in r]
    if len(done) == len(rows):
        avg = lambda k: sum(r[k] for r in rows) / len(rows)
        lines.append(f"| AVG | {avg('aoe'):.2f} | {avg('foe'):.2f} | {avg('paper_aoe'):.2f} | "
                     f"{avg('paper_foe'):.2f} | - | - |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", default="runs", help="folder of work directories (default: runs)")
    parser.add_argument("--output", default="deterministic", choices=("deterministic", "gaussian"))
    parser.add_argument("--epochs", type=int, default=200, help="epochs of the runs (default: 200)")
    parser.add_argument("--seed", type=int, default=1000, help="seed of the runs (default: 1000)")
    parser.add_argument("--evaluate", action="store_true", help="evaluate runs not yet evaluated")
    parser.add_argument("--json", action="store_true", help="print rows as JSON")
    args = parser.parse_args()
    rows = collect(Path(args.runs), args.output, args.epochs, args.seed, args.evaluate)
    print(json.dumps(rows, indent=2) if args.json else markdown(rows, args.output))


if __name__ == "__main__":
    main()
