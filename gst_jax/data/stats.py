"""Window and pedestrian counts per scene and split (the schema of reference_windows.json)."""

from __future__ import annotations

import dataclasses
from typing import Any

from gst_jax.config import DataConfig, TimeGrid
from gst_jax.data.protocols import has_validation, load_split, why_no_window


def split_stats(config: DataConfig, scenes: list[str], grid: TimeGrid = TimeGrid()) -> dict:
    """`{"protocol": ..., "scenes": {scene: {split: {windows, pedestrian_slots,
    max_pedestrians, fully_detected}}}, "files_without_windows": {"scene/split": {file:
    why}}}` for the given scenes; the last names the files that gave a split no window, and
    why (`why_no_window`)."""
    splits = ("train", "val", "test") if has_validation(config) else ("train", "test")
    result: dict[str, Any] = {
        "protocol": f"{config.protocol}, obs {grid.obs_len}, pred {grid.pred_len}",
        "scenes": {}, "files_without_windows": {}}
    for scene in scenes:
        scene_config = dataclasses.replace(config, scene=scene)
        result["scenes"][scene] = {}
        for split in splits:
            window_set = load_split(scene_config, split, grid)
            result["scenes"][scene][split] = window_set.stats()
            if empty := window_set.files_without_windows():
                result["files_without_windows"][f"{scene}/{split}"] = {
                    path: why_no_window(path, scene_config, split, grid) for path in empty}
    return result


def format_stats(stats: dict) -> str:
    """An aligned table, with the share of partially detected pedestrians."""
    header = ("scene", "split", "windows", "pedestrians", "max", "fully detected", "partial")
    rows = []
    for scene, splits in stats["scenes"].items():
        for split, s in splits.items():
            slots = s["pedestrian_slots"]
            partial = 1 - s["fully_detected"] / slots if slots else 0.0
            rows.append((scene, split, s["windows"], slots, s["max_pedestrians"],
                         s["fully_detected"], f"{100 * partial:.1f}%"))
    widths = [max(len(str(r[i])) for r in (header, *rows)) for i in range(len(header))]
    lines = [f"protocol: {stats['protocol']}"]
    for row in (header, *rows):
        lines.append("  ".join(str(c).rjust(w) if i >= 2 else str(c).ljust(w)
                               for i, (c, w) in enumerate(zip(row, widths))))
    for name, files in stats.get("files_without_windows", {}).items():
        lines += [f"note: {path} gives {name} no window: {why}" for path, why in files.items()]
    return "\n".join(lines)
