"""Figures of the paper's tables, of the schedule check and of the comparative study across
datasets (Figs. 4-6): errors against n per detection mode with every seed, the paired
differences of partial over fully detected and of sparse over full connection, improvement of
the best sparse n over full connection against crowd density, the best n per dataset; Table I
as bars (ours, the paper's and constant velocity per scene), and a shorter schedule's change
from the paper's per scene."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from gst_jax.figures import DETECTION_STYLE, n_label, plt, save


def errors_against_n_per_seed(all_results: Sequence[dict], path: Path) -> Path:
    """The paper's Fig. 4, a row per scene: AOE and FOE against n, one line per detection
    mode (mean over seeds), every seed a dot, constant velocity dashed."""
    fig, axes = plt.subplots(len(all_results), 2, figsize=(7.0, 2.6 * len(all_results)),
                             squeeze=False, gridspec_kw=dict(wspace=0.3))
    for row, results in zip(axes, all_results):
        heads = sorted({m["edge_heads"] for m in results["members"]})
        x = {n: i for i, n in enumerate(heads)}
        for ax, metric in zip(row, ("aoe", "foe")):
            for detection, style in DETECTION_STYLE.items():
                cells = sorted((c for c in results["table"] if c["detection"] == detection),
                               key=lambda c: c["edge_heads"])
                if not cells:
                    continue
                ax.plot([x[c["edge_heads"]] for c in cells], [c[metric] for c in cells],
                        label=f"{detection} detection", **style)
                seeds = [m for m in results["members"]
                         if m["fully_detected_only"] == (detection == "full")]
                ax.scatter([x[m["edge_heads"]] for m in seeds], [m[metric] for m in seeds],
                           s=10, alpha=0.5, color=style["color"])
            ax.axhline(results["table"][0][f"cv_{metric}"], color="gray", ls="--", lw=1,
                       label="constant velocity")
            ax.set_xticks(range(len(heads)), [n_label(n) for n in heads])
            ax.set_xlabel("n (F = full connection)")
            ax.set_ylabel(f"{results['scene']}: {metric.upper()} (m)")
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(all_results[0]["protocol"].split(", seeds")[0] + "; dots: seeds", fontsize=7)
    return save(fig, path)


def paired_gains(differences: dict[str, list[dict]], path: Path) -> Path:
    """The paper's Fig. 6 as paired differences (lower favours the paper): AOE of partial
    minus fully detected per n, AOE of sparse n minus full connection, and the freezing rate
    of sparse n minus full connection on the same encounters; a bar per (scene, n, mode) at
    the mean over seeds, every seed a dot."""
    panels = [("partial", "aoe", "AOE: partial - fully detected (m)"),
              ("sparse", "aoe", "AOE: n - full connection (m)"),
              ("freezing", "freezing", "freezing: n - full connection")]
    panels = [panel for panel in panels if differences.get(panel[0])]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.0 * len(panels), 2.8), squeeze=False,
                             gridspec_kw=dict(wspace=0.35))
    for ax, (claim, key, label) in zip(axes[0], panels):
        groups: dict[tuple, list[float]] = {}
        for d in differences[claim]:
            groups.setdefault((d["scene"], d["edge_heads"], d["detection"] or ""), []).append(
                d[key])
        keys = sorted(groups)
        for i, (scene, n, detection) in enumerate(keys):
            values = groups[(scene, n, detection)]
            color = DETECTION_STYLE[detection]["color"] if detection else "tab:green"
            ax.bar(i, np.mean(values), 0.7, color=color, alpha=0.5)
            ax.scatter([i] * len(values), values, s=10, color=color)
        ax.set_xticks(range(len(keys)), [f"{s}\nn={n_label(n)}\n{d}" for s, n, d in keys],
                      fontsize=6)
        ax.axhline(0, color="black", lw=0.8)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    return save(fig, path)


def sparse_gain_against_density(all_results: Sequence[dict], path: Path) -> Path:
    """Improvement of the best sparse n over full connection against crowd density."""
    fig, ax = plt.subplots(figsize=(3.6, 2.8))
    for r in all_results:
        gain = r.get("sparse_vs_full_connection_partial")
        if gain:
            ax.scatter(r["density"], gain["aoe_pct"], color="tab:blue")
            ax.annotate(r["scene"], (r["density"], gain["aoe_pct"]), fontsize=7,
                        xytext=(3, 3), textcoords="offset points")
    ax.axhline(0, color="black", lw=0.8)
    ax.set_xlabel("partially detected pedestrians per window")
    ax.set_ylabel("AOE improvement, best\nsparse n over full (%)")
    ax.grid(alpha=0.3)
    return save(fig, path)


def best_n_per_dataset(all_results: Sequence[dict], path: Path) -> Path:
    """Bar per dataset: the best sparse n (by AOE, partial detection)."""
    fig, ax = plt.subplots(figsize=(3.6, 2.8))
    rows = [(r["scene"], r["best_n_partial"]) for r in all_results if "best_n_partial" in r]
    ax.bar([s for s, _ in rows], [n for _, n in rows], color="tab:blue")
    ax.set_yscale("log", base=2)
    ax.set_ylabel("best n")
    ax.grid(axis="y", alpha=0.3)
    return save(fig, path)


def table1_against_paper(rows: Sequence[dict], path: Path, title: str,
                         paper_label: str = "paper") -> Path:
    """Grouped bars per scene, AOE and FOE: ours (± spread), the paper's, constant velocity.

    rows: experiments/table1.py's rows; a scene without a finished run has no "ours" bar
    and is marked "missing".
    """
    fig, axes = plt.subplots(1, 2, figsize=(8.0, 2.8))
    x = np.arange(len(rows))
    width = 0.27
    for ax, metric in zip(axes, ("aoe", "foe")):
        ours = [r.get(metric, np.nan) for r in rows]
        ax.bar(x - width, ours, width, yerr=[r.get(f"{metric}_spread", 0.0) for r in rows],
               capsize=2, color="tab:blue", label="ours")
        ax.bar(x, [r[f"paper_{metric}"] for r in rows], width, color="tab:gray", label=paper_label)
        ax.bar(x + width, [r[f"cv_{metric}"] for r in rows], width, color="tab:orange",
               label="constant velocity")
        for i, r in enumerate(rows):
            if metric not in r:
                ax.text(x[i] - width, 0.02, "missing", rotation=90, fontsize=6,
                        ha="center", va="bottom")
        ax.set_xticks(x, [r["scene"] for r in rows])
        ax.set_ylabel(f"{metric.upper()} (m)")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=8)
    return save(fig, path)


def schedule_against_paper(rows_by_candidate: dict[str, Sequence[dict]], path: Path) -> Path:
    """Grouped bars per scene, AOE and FOE: the change (%) of each shorter schedule's mean over
    seeds from the 200-epoch paper schedule (± its seed std), a tick at what is allowed.

    rows_by_candidate: experiments/schedules.py's rows per candidate ('compressed:100').
    """
    fig, axes = plt.subplots(1, 2, figsize=(8.6, 2.8), gridspec_kw=dict(wspace=0.4))
    candidates = list(rows_by_candidate)
    scenes = [row["scene"] for row in rows_by_candidate[candidates[0]]]
    x = np.arange(len(scenes))
    width = 0.8 / len(candidates)
    for ax, metric in zip(axes, ("aoe", "foe")):
        for k, name in enumerate(candidates):
            rows = rows_by_candidate[name]
            scale = [100 / row["reference"][metric] for row in rows]
            ax.bar(x + (k - (len(candidates) - 1) / 2) * width,
                   [row.get(f"{metric}_change_pct", np.nan) for row in rows], width,
                   yerr=[row.get(f"{metric}_spread", 0.0) * s for row, s in zip(rows, scale)],
                   capsize=2, label=name)
        allowed = [100 * (row[f"{metric}_allowed"] / row["reference"][metric] - 1)
                   for row in rows_by_candidate[candidates[0]] if f"{metric}_allowed" in row]
        if len(allowed) == len(scenes):
            ax.scatter(x, allowed, marker="_", s=400, color="black", label="allowed", zorder=3)
        ax.axhline(0, color="black", lw=0.8)
        ax.set_xticks(x, scenes)
        ax.set_ylabel(f"{metric.upper()} change from\n200 epochs (%)")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("GST (D) n = 1, paper protocol: shorter schedules against the paper's 200 "
                 "epochs", fontsize=8)
    return save(fig, path)
