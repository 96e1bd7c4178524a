"""Where does GST beat constant velocity? Per-pedestrian errors of GST, constant velocity and
a linear regression on each scene's test split, binned by the future's non-linearity and by
what a planner sees during the observation (gst_jax.strata):

    python experiments/strata.py                      # runs/strata/strata.{md,json,png}
    python experiments/strata.py --publish            # results/strata.{md,json,png}

Models: each ETH/UCY scene's shipped Table I model (`pretrained:<scene>_d`, trained on that
scene's paper train split) on its paper test split, and the general model
(`pretrained:crowd_d`, trained on the seven scenes' train splits) on all seven test splits;
20 samples (hard, tau 0.03), the error of a pedestrian the mean over them (so that the mean
over pedestrians is the paper's AOE / FOE). Each (model, scene) is kept in
<out>/runs/strata-<model>-<scene>.npz once predicted, so that a second run only tabulates.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import numpy as np

from _common import add_results_flags, results_folder
from gst_jax import data, strata
from gst_jax.config import DataConfig
from gst_jax.evaluation import predict_windows
from gst_jax.figures import plt, save
from gst_jax.progress import Progress
from gst_jax.runs import load_model

SCENES = ("eth", "hotel", "univ", "zara1", "zara2")
GENERAL_SCENES = SCENES + ("lcas", "wildtrack")
SAMPLES, SEED = 20, 0
FEATURES = {"nonlinearity": "distance of the true endpoint from the CV extrapolation (m)",
            "closest": "closest other pedestrian during the observation (m)",
            "neighbours": "most people within 2 m at one observed step"}


def records_of(model: str, scene: str, out: Path, progress: Progress, split: str = "test",
               label: str | None = None) -> dict[str, np.ndarray]:
    """The per-pedestrian records of `model` on `scene`'s paper `split` (cached as `label`,
    by default the pretrained model's name); "val" is paper-val's, the end of each file's
    paper train windows (those the shipped models were trained on: in-sample for them)."""
    label = label or model.split(":")[-1]
    name = f"strata-{label}-{scene}" + ("" if split == "test" else f"-{split}")
    path = out / "runs" / f"{name}.npz"
    if path.exists():
        with np.load(path) as cached:
            return dict(cached)
    run = load_model(model)
    protocol = "paper-val" if split == "val" else "paper"
    window_set = data.load_split(DataConfig(scene=scene, protocol=protocol), split,
                                 run.model_config.grid)
    predicted = predict_windows(run.params, jax.random.key(SEED), window_set, run.model_config,
                                num_samples=SAMPLES, progress=progress)
    records = strata.pedestrian_records(predicted, run.model_config.obs_len)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **records)
    return records


def pooled(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def interval(cell: dict) -> str:
    return f"{cell['mean']:+.3f} [{cell['low']:+.3f}, {cell['high']:+.3f}]"


def markdown(tables: dict) -> str:
    lines = ["# Where GST beats constant velocity", "",
             "Paper protocol, each scene's test split, fully detected pedestrians, "
             f"{SAMPLES} samples (hard, tau 0.03); errors in metres, per pedestrian the mean "
             "over the samples. GST (D): the shipped Table I model of each scene; general: "
             "`pretrained:crowd_d` on all seven scenes. Linear: least squares over the 8 "
             "observed steps, extrapolated. Differences are GST minus the baseline on the "
             "same pedestrians (negative: GST better), with 95 % intervals over pedestrians; "
             "bin edges fixed before any result was seen. Made by "
             "`python experiments/strata.py --publish`."]
    for table in tables.values():
        lines += ["", f"## {table['title']}", "",
                  "| scene | pedestrians | GST ADE | CV ADE | linear ADE | GST - CV ADE | "
                  "GST - CV FDE |", "|---|---|---|---|---|---|---|"]
        for scene, row in table["scenes"].items():
            lines.append(f"| {scene} | {row['count']} | {row['model_ade']:.3f} | "
                         f"{row['cv_ade']:.3f} | {row['linear_ade']:.3f} | "
                         f"{interval(row['model_minus_cv_ade'])} | "
                         f"{interval(row['model_minus_cv_fde'])} |")
        for feature, bins in table["strata"].items():
            lines += ["", f"{FEATURES[feature]}, all scenes pooled:", "",
                      "| bin | pedestrians | GST ADE | CV ADE | linear ADE | GST - CV ADE | "
                      "GST - linear ADE | GST - CV FDE |", "|---|---|---|---|---|---|---|---|"]
            for b in bins:
                lines.append(f"| [{b['low']:g}, {b['high']:g}) | {b['count']} | "
                             f"{b['model_ade']:.3f} | {b['cv_ade']:.3f} | "
                             f"{b['linear_ade']:.3f} | {interval(b['model_minus_cv_ade'])} | "
                             f"{interval(b['model_minus_linear_ade'])} | "
                             f"{interval(b['model_minus_cv_fde'])} |")
    return "\n".join(lines) + "\n"


def figure(tables: dict, path: Path) -> Path:
    """Per feature (columns) and model (rows): GST - CV ADE per bin with its interval."""
    fig, axes = plt.subplots(len(tables), len(FEATURES), figsize=(11, 3.2 * len(tables)),
                             squeeze=False)
    for row, table in zip(axes, tables.values()):
        for ax, feature in zip(row, FEATURES):
            bins = table["strata"][feature]
            means = [b["model_minus_cv_ade"]["mean"] for b in bins]
            errors = [b["model_minus_cv_ade"]["high"] - m for b, m in zip(bins, means)]
            labels = [f"[{b['low']:g}, {b['high']:g})\nn={b['count']}" for b in bins]
            ax.bar(range(len(bins)), means, yerr=errors, color="tab:blue", capsize=3)
            ax.axhline(0, color="k", lw=0.8)
            ax.set_xticks(range(len(bins)), labels, fontsize=7)
            ax.set_title(f"{table['title'].split(':')[0]}\n{FEATURES[feature]}", fontsize=8)
            ax.set_ylabel("GST - CV ADE (m)", fontsize=8)
    fig.tight_layout()
    return save(fig, path)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_results_flags(parser, "strata", "strata.md/.json/.png and the cached records runs/",
                      runs=False)
    args = parser.parse_args(argv)
    out = results_folder(args)
    progress = Progress()
    cases = {"scene": ("Each scene's own model: GST (D), Table I", SCENES, "pretrained:{}_d"),
             "general": ("The general model: crowd_d", GENERAL_SCENES, "pretrained:crowd_d")}
    tables = {}
    for name, (title, scenes, model) in cases.items():
        parts = {s: records_of(model.format(s), s, out, progress) for s in scenes}
        everything = pooled(list(parts.values()))
        scene_rows = {s: strata.stratify(r, "nonlinearity", (0.0, np.inf))[0]
                      for s, r in parts.items()}
        scene_rows["all"] = strata.stratify(everything, "nonlinearity", (0.0, np.inf))[0]
        tables[name] = {"title": title, "scenes": scene_rows,
                        "strata": {f: strata.stratify(everything, f) for f in FEATURES}}
    out.mkdir(parents=True, exist_ok=True)
    (out / "strata.json").write_text(json.dumps(tables, indent=1, default=float) + "\n")
    (out / "strata.md").write_text(markdown(tables))
    figure(tables, out / "strata.png")
    print(json.dumps(tables, indent=1, default=float) if args.json else markdown(tables))


if __name__ == "__main__":
    main()
