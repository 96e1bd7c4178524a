"""Figures (matplotlib, Agg backend) from results already computed; nothing here is jitted.

Sweep figures in the spirit of the paper's Figs. 4-6: errors against n for one scene,
improvement of partial over fully detected observation per dataset and n, improvement of
the best sparse n over full connection against crowd density, and the best n per dataset.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

DETECTION_STYLE = {"partial": dict(color="tab:blue", marker="o"),
                   "full": dict(color="tab:orange", marker="s")}


def _n_label(n: int) -> str:
    return "F" if n == 0 else str(n)


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return path


def errors_against_n(results: dict, path: Path) -> Path:
    """AOE and FOE (mean +- std over seeds) against n, one line per detection mode."""
    fig, axes = plt.subplots(1, 2, figsize=(7.0, 2.8), sharex=True)
    for detection, style in DETECTION_STYLE.items():
        rows = sorted((r for r in results["table"] if r["detection"] == detection),
                      key=lambda r: r["edge_heads"])
        if not rows:
            continue
        x = range(len(rows))
        for ax, metric in zip(axes, ("aoe", "foe")):
            ax.errorbar(x, [r[metric] for r in rows], yerr=[r[metric + "_std"] for r in rows],
                        label=f"{detection} detection", capsize=3, **style)
            ax.set_xticks(list(x), [_n_label(r["edge_heads"]) for r in rows])
    for ax, metric in zip(axes, ("AOE", "FOE")):
        ax.set_xlabel("n (F = full connection)")
        ax.set_ylabel(f"{metric} (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{results['scene']}: {results['protocol']}", fontsize=7)
    return _save(fig, path)


def partial_vs_full_detection(all_results: Sequence[dict], path: Path) -> Path:
    """Grouped bars: AOE improvement (%) of partial over fully detected, per dataset and n."""
    fig, ax = plt.subplots(figsize=(7.0, 2.8))
    scenes = [r["scene"] for r in all_results]
    heads = sorted({int(n) for r in all_results for n in r["partial_vs_fully_detected"]})
    width = 0.8 / max(len(heads), 1)
    for k, n in enumerate(heads):
        values = [r["partial_vs_fully_detected"].get(str(n), {}).get("aoe_pct", float("nan"))
                  for r in all_results]
        ax.bar([i + k * width for i in range(len(scenes))], values, width, label=f"n={_n_label(n)}")
    ax.axhline(0, color="black", lw=0.8)
    ax.set_xticks([i + 0.4 - width / 2 for i in range(len(scenes))], scenes)
    ax.set_ylabel("AOE improvement,\npartial over full (%)")
    ax.legend(fontsize=7, ncol=len(heads))
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


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
    return _save(fig, path)


def best_n_per_dataset(all_results: Sequence[dict], path: Path) -> Path:
    """Bar per dataset: the best sparse n (by AOE, partial detection)."""
    fig, ax = plt.subplots(figsize=(3.6, 2.8))
    rows = [(r["scene"], r["best_n_partial"]) for r in all_results if "best_n_partial" in r]
    ax.bar([s for s, _ in rows], [n for _, n in rows], color="tab:blue")
    ax.set_yscale("log", base=2)
    ax.set_ylabel("best n")
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)
