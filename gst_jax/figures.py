"""Figures (matplotlib, Agg backend) from results already computed; nothing here is jitted.

Fig. 3 (a prediction with its sampled graphs), one agent's attention over time, training
curves, a sweep's errors against n (the paper's Fig. 4 for one scene), and conformal regions
over a scene with their coverage. The figures of the tables and the cross-dataset study are
experiments/_figures.py's.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib
import numpy as np

# Figures are files, never windows: the one place matplotlib is set up, for every figure of
# the package (gst_jax.simulate.paper.figures imports `plt` and `save` from here).
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

DETECTION_STYLE = {"partial": dict(color="tab:blue", marker="o"),
                   "full": dict(color="tab:orange", marker="s")}


def n_label(n: int) -> str:
    return "F" if n == 0 else str(n)


def save(fig, path: Path, dpi: int = 150) -> Path:
    """Write `fig` to `path` (creating its folder) and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
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
            ax.set_xticks(list(x), [n_label(r["edge_heads"]) for r in rows])
    for ax, metric in zip(axes, ("AOE", "FOE")):
        ax.set_xlabel("n (F = full connection)")
        ax.set_ylabel(f"{metric} (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{results['scene']}: {results['protocol']}", fontsize=7)
    return save(fig, path)


# --- Seeing one prediction (the paper's Fig. 3) ------------------------------------------

# A sampled edge whose selection probability is below this was drawn from a row of zeros (the
# release's attention underflowed, docs/MODEL.md 2.1): by the Gumbel noise alone.
NOISE_DRAWN_BELOW = 1e-6
SAMPLED_EDGES_CAPTION = (
    "Sampled edges (arrows, black cells): sample 0's graph, Gumbel-softmax draws from the "
    "selection probabilities (the edge selector's, docs/MODEL.md 2.1), along which the encoder "
    "attends, with weights not drawn here. Selection probability: mean over the n heads, as "
    "`plot attention` and experiments/selector_alive.py measure it; a dashed pink edge was "
    "drawn with selection probability 0, by the noise alone.")


def scene_prediction(observed, observed_mask, future, future_mask, samples, predicted_mask,
                     fully_detected, adjacency_steps, step_labels, path: Path,
                     title: str = "") -> Path:
    """Trajectories (top), sampled graphs (middle) and adjacency matrices (bottom), with
    SAMPLED_EDGES_CAPTION beneath.

    observed (T, N, 2) / observed_mask (T, N); future (P, N, 2) / future_mask (P, N);
    samples (K, P, N, 2) predicted positions; predicted_mask, fully_detected (N,) bool;
    adjacency_steps: one (sampled adjacency (N, N+1) ghost last, selection probabilities
    (N, N+1), positions (N, 2), velocities (N, 2), present (N,) bool) per graph column, titled
    by step_labels.
    """
    columns = len(adjacency_steps)
    fig = plt.figure(figsize=(3.2 * columns, 9.0))
    grid = fig.add_gridspec(3, columns, height_ratios=[1.3, 1, 1])
    ax = fig.add_subplot(grid[0, :])
    num = observed.shape[1]
    for i in range(num):
        seen = observed_mask[:, i] > 0
        ax.plot(observed[seen, i, 0], observed[seen, i, 1], "-", color="tab:blue", lw=1.2)
        truth = future_mask[:, i] > 0
        ax.plot(future[truth, i, 0], future[truth, i, 1], "-", color="tab:green", lw=1.2)
        if predicted_mask[i]:
            color = "tab:red" if fully_detected[i] else "tab:orange"
            for sample in samples[:, :, i]:
                ax.plot(sample[:, 0], sample[:, 1], "-", color=color, lw=0.5, alpha=0.2)
            mean = samples[:, :, i].mean(axis=0)
            ax.plot(mean[:, 0], mean[:, 1], "-", color=color, lw=2.0)
    handles = [plt.Line2D([], [], color=c, label=label) for c, label in (
        ("tab:blue", "observed"), ("tab:green", "ground truth"),
        ("tab:red", "prediction (fully detected)"), ("tab:orange", "prediction (partial)"))]
    ax.legend(handles=handles, fontsize=7, loc="best")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=8)
    for c, ((adjacency, selection, positions, velocities, present), label) in enumerate(
            zip(adjacency_steps, step_labels)):
        graph_ax = fig.add_subplot(grid[1, c])
        graph_ax.scatter(positions[present, 0], positions[present, 1], s=12, color="black")
        graph_ax.quiver(positions[present, 0], positions[present, 1], velocities[present, 0],
                        velocities[present, 1], color="tab:gray", angles="xy",
                        scale_units="xy", scale=0.5, width=0.004)
        sampled = [(target, neighbour) for target in range(num) for neighbour in range(num)
                   if present[target] and adjacency[target, neighbour] > 0.5
                   and neighbour != target]
        drawn = [(target, neighbour) for target, neighbour in sampled if present[neighbour]]
        for target, neighbour in drawn:
            by_noise = selection[target, neighbour] < NOISE_DRAWN_BELOW
            graph_ax.annotate("", xy=positions[neighbour], xytext=positions[target],
                              arrowprops=dict(arrowstyle="->", lw=1,
                                              color="tab:pink" if by_noise else "tab:purple",
                                              linestyle="--" if by_noise else "-"))
        graph_ax.set_aspect("equal", adjustable="datalim")
        chance = (f"selection probability of these edges: mean "
                  f"{np.mean([selection[e] for e in drawn]):.2f}" if drawn
                  else "no edge sampled to another person")
        if absent := len(sampled) - len(drawn):     # padding, or nobody there at this step
            chance += f"\n{absent} more sampled to empty slots (not drawn)"
        graph_ax.set_title(f"sampled edges, {label}\n{chance}", fontsize=8)
        matrix_ax = fig.add_subplot(grid[2, c])
        matrix_ax.imshow(adjacency[:num], cmap="Greys", vmin=0, vmax=1)
        every = 1 if num <= 16 else 5
        ticks = list(range(0, num, every))
        matrix_ax.set_xticks(ticks + [num], [str(j) for j in ticks] + ["g"], fontsize=6)
        matrix_ax.set_yticks(ticks, [str(i) for i in ticks], fontsize=6)
        matrix_ax.set_xlabel("neighbour (g = ghost)", fontsize=7)
        matrix_ax.set_ylabel("target", fontsize=7)
        matrix_ax.set_title("sampled edges (black)", fontsize=7)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.text(0.5, 0.005, SAMPLED_EDGES_CAPTION, ha="center", va="bottom", fontsize=6.5,
             wrap=True)
    return save(fig, path)


def attention_over_time(probabilities, present, agent: int, obs_len: int, step_s: float,
                        path: Path, title: str = "", max_neighbours: int = 6) -> Path:
    """One agent's selection probability of each neighbour and of the ghost per selector call.

    probabilities (S, N+1) (ghost last); present (N,) bool: neighbours to draw.
    """
    fig, ax = plt.subplots(figsize=(6.0, 2.8))
    steps = range(1, probabilities.shape[0] + 1)
    candidates = [j for j in range(probabilities.shape[1] - 1) if present[j] and j != agent]
    # The most attended neighbours get a line each; crowds would drown the legend.
    shown = sorted(candidates, key=lambda j: -probabilities[:, j].max())[:max_neighbours]
    for j in sorted(shown):
        ax.plot(steps, probabilities[:, j], label=f"pedestrian {j}", lw=1.2)
    rest = [j for j in candidates if j not in shown]
    if rest:
        ax.plot(steps, probabilities[:, rest].sum(axis=1), color="tab:gray", lw=1.0,
                label=f"{len(rest)} others (sum)")
    ax.plot(steps, probabilities[:, -1], "k--", label="ghost", lw=1.5)
    ax.axvline(obs_len + 0.5, color="tab:gray", lw=0.8)
    ax.text(obs_len + 0.7, 0.95, "prediction", fontsize=7, va="top")
    ax.set_xlabel(f"selector call ({step_s:g} s steps)")
    ax.set_ylabel(f"selection probability, agent {agent}")
    ax.set_ylim(0, 1.02)
    ax.legend(fontsize=6, ncol=2)
    ax.set_title(title, fontsize=8)
    ax.grid(alpha=0.3)
    return save(fig, path)


def training_curves(records: Sequence[dict], path: Path, title: str = "") -> Path:
    """Loss per epoch, and validation AOE/FOE where the run recorded them."""
    validated = [r for r in records if "val_aoe" in r]
    fig, axes = plt.subplots(1, 2 if validated else 1, figsize=(7.0 if validated else 3.6, 2.8),
                             squeeze=False)
    axes[0, 0].plot([r["epoch"] for r in records], [r["loss"] for r in records])
    axes[0, 0].set_xlabel("epoch")
    axes[0, 0].set_ylabel("training loss")
    axes[0, 0].grid(alpha=0.3)
    if validated:
        epochs = [r["epoch"] for r in validated]
        axes[0, 1].plot(epochs, [r["val_aoe"] for r in validated], "o-", label="AOE")
        axes[0, 1].plot(epochs, [r["val_foe"] for r in validated], "s-", label="FOE")
        axes[0, 1].set_xlabel("epoch")
        axes[0, 1].set_ylabel("validation error (m)")
        axes[0, 1].legend(fontsize=7)
        axes[0, 1].grid(alpha=0.3)
    fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    return save(fig, path)


def conformal_regions(history, futures, radii, truth, coverage, radius, alpha: float,
                      step_s: float, path: Path, title: str = "", most_tracks: int = 6) -> Path:
    """One frame's predictions with their conformal discs (left: the `most_tracks` tracks
    nearest the frame's centre, discs every third step) and the long-run coverage and mean
    radius per horizon step (right).

    history (L, T, 2) NaN where not detected; futures (L, P, 2); radii (L, P) metres; truth
    (L, P, 2) NaN where not observed; coverage, radius (P,).
    """
    fig, (scene_ax, coverage_ax) = plt.subplots(1, 2, figsize=(11, 4.6),
                                                gridspec_kw=dict(width_ratios=[1.3, 1]))
    now = history[:, -1]
    shown = np.argsort(np.linalg.norm(now - np.median(now, axis=0), axis=-1))[:most_tracks]
    horizon = futures.shape[1]
    steps = list(range(2, horizon, 3)) or [horizon - 1]
    colors = plt.get_cmap("viridis")(np.linspace(0.15, 0.85, len(steps)))
    for track in shown:
        scene_ax.plot(*history[track].T, "-", color="tab:blue", lw=1.5)
        scene_ax.plot(*truth[track].T, "-", color="tab:green", lw=1.5)
        scene_ax.plot(*futures[track].T, ".-", color="tab:red", lw=1.0, ms=3)
        for color, k in zip(colors, steps):
            if np.isfinite(radii[track, k]):
                scene_ax.add_patch(plt.Circle(futures[track, k], radii[track, k], fill=False,
                                              color=color, lw=1.0, alpha=0.8))
    handles = [plt.Line2D([], [], color=c, label=label) for c, label in (
        ("tab:blue", "observed"), ("tab:green", "what happened"), ("tab:red", "predicted"))]
    handles += [plt.Line2D([], [], color=c, marker="o", ls="", mfc="none",
                           label=f"disc at {(k + 1) * step_s:.1f} s")
                for c, k in zip(colors, steps)]
    scene_ax.legend(handles=handles, fontsize=7, loc="best")
    scene_ax.set_aspect("equal", adjustable="datalim")
    scene_ax.autoscale_view()
    scene_ax.set_xlabel("x (m)")
    scene_ax.set_ylabel("y (m)")
    scene_ax.set_title(title, fontsize=8)
    seconds = step_s * np.arange(1, len(coverage) + 1)
    coverage_ax.plot(seconds, coverage, "o-", color="tab:purple", label="coverage")
    coverage_ax.axhline(1 - alpha, color="gray", ls="--", lw=1, label=f"target {1 - alpha:.2f}")
    coverage_ax.set_ylim(min(0.5, float(np.min(coverage)) - 0.05), 1.0)
    coverage_ax.set_xlabel("horizon (s)")
    coverage_ax.set_ylabel("long-run coverage")
    radius_ax = coverage_ax.twinx()
    radius_ax.plot(seconds, radius, "s:", color="tab:orange", label="mean radius")
    radius_ax.set_ylabel("mean radius (m)")
    lines = coverage_ax.get_legend_handles_labels(), radius_ax.get_legend_handles_labels()
    coverage_ax.legend(lines[0][0] + lines[1][0], lines[0][1] + lines[1][1], fontsize=7,
                       loc="lower left")
    fig.tight_layout()
    return save(fig, path)
