"""What `python -m gst_jax.conformal` prints and draws of a coverage result
(`gst_jax.coverage.play`): the table per horizon step and the figure of a snapshot's discs."""

from __future__ import annotations

from gst_jax.coverage import Snapshot
from gst_jax.figures import conformal_regions


def draw(snapshot: Snapshot, result: dict, path, title: str):
    """The snapshot's regions and the coverage per horizon step, as a figure at `path`."""
    return conformal_regions(snapshot.history, snapshot.futures, snapshot.radii,
                             snapshot.truth, result["coverage"], result["radius"],
                             result.get("step_alpha", result["alpha"]), result["step_s"], path,
                             title)


def format_table(result: dict) -> str:
    """`play`'s result (with model, scene and split) as the command prints it: per horizon
    step the coverage, mean radius and the number of scores T; for ACI its bound, a figure
    outside it marked with "!"; then the whole-horizon coverage."""
    lines = [f"{result['model']} on {result['scene']} ({result['split']} split, "
             f"{result['frames']} frames, the first {result['calibration_frames']} calibrating): "
             f"{result['method']}, alpha {result['alpha']}"
             + (f" (Bonferroni: {result['step_alpha']:.4g} a step)" if result["bonferroni"]
                else "")
             + (f", gamma {result['gamma']}" if result.get("bound") else ""),
             "  step     s  coverage  radius (m)  scores (T)" +
             ("     bound" if result.get("bound") else "")]
    target = 1 - result.get("step_alpha", result["alpha"])
    for k, (c, r, n) in enumerate(zip(result["coverage"], result["radius"], result["scores"])):
        line = f"  {k + 1:4d} {(k + 1) * result['step_s']:5.2f}  {c:8.3f}  {r:10.3f}  {n:10d}"
        if result.get("bound"):
            bound = result["bound"][k]
            line += f"  +-{bound:7.3f}" + (" !" if abs(c - target) > bound else "")
        lines.append(line)
    lines.append(f"  all {len(result['coverage'])} steps inside their discs: "
                 f"{result['joint_coverage']:.3f} of {result['joint_predictions']} predictions")
    return "\n".join(lines)
