"""Which windows are train, validation and test under each protocol (numpy only).

- `paper`: the GST release's per-file temporal split: window starts
  i < int((num_windows + 1) * 0.8) train, the rest test. Reproduces the release's counts.
- `paper-val`: the same test split; the last `val_fraction` of each file's train windows
  become validation, and train windows that share any frame with them are dropped.
- `loo`: leave-one-scene-out (Social-GAN split, `data/eth_ucy/loo/splits.json`).
TrajNet++ crowds (`lcas`, `wildtrack`), `crowd` (all seven scenes' files) and your own files
(`DataConfig.data`) follow `paper` / `paper-val` on each file; the split `all` is every window
of every file.
"""

from __future__ import annotations

import functools
import glob
import json
import math
import os
import re
from pathlib import Path

from gst_jax.config import (
    CROWD,
    CROWD_SCENES,
    ETH_UCY_SCENES,
    PROTOCOLS,
    SCENES,
    TRAJNET_SCENES,
    DataConfig,
    TimeGrid,
)
from gst_jax.data.checks import check_speeds, longest_track
from gst_jax.data.readers import Tracks, read_tracks, to_model_rate
from gst_jax.data.windows import Window, WindowSet, cut_windows, kept
from gst_jax.errors import DataError

__all__ = ["bundled_or_local", "data_files", "data_name", "default_data_dir", "has_validation",
           "load_split", "no_windows_message", "scene_files", "split_files", "split_frames",
           "why_no_window"]

SPLITS = ("train", "val", "test", "all")
TRACK_SUFFIXES = (".txt", ".csv", ".ndjson")
# Characters a run's name cannot hold: ':' splits DIR:MEMBER model names; the rest break
# paths on some system (Windows forbids all of them), as do control characters.
_UNSAFE_IN_NAMES = re.compile(r'[:<>"/\\|?*\x00-\x1f]+')
TRAJNET_FILES = {scene: f"{scene}.ndjson" for scene in TRAJNET_SCENES}


def default_data_dir() -> Path:
    """The bundled datasets (--data-dir names another folder): the copy inside an installed
    package (gst_jax/datasets, the repository's data/), or, in a checkout or an editable
    install, the repository's data/ itself."""
    installed = Path(__file__).resolve().parents[1] / "datasets"
    return installed if installed.is_dir() else Path(__file__).resolve().parents[2] / "data"


def scene_files(data_dir: Path, scene: str) -> list[Path]:
    """The raw files of a scene for the paper protocol (univ has two; crowd all of them)."""
    if scene == CROWD:
        return [path for one in CROWD_SCENES for path in scene_files(data_dir, one)]
    if scene in TRAJNET_FILES:
        return [data_dir / "trajnetpp" / TRAJNET_FILES[scene]]
    files = sorted((data_dir / "eth_ucy" / "raw" / scene).glob("*.txt"))
    if not files:
        raise DataError(f"no raw files for scene {scene!r} under {data_dir / 'eth_ucy' / 'raw'}")
    return files


def data_files(pattern: str) -> list[Path]:
    """Your own files: one file, every .txt / .csv / .ndjson in a folder, or a glob's matches. A
    relative path that names nothing here but a file or folder of the bundled data is that
    (e.g. samples/crowd_10hz.txt, from any folder)."""
    path = bundled_or_local(pattern)
    if path.is_file():
        if path.suffix not in TRACK_SUFFIXES:
            raise DataError(f"{path}: not a trajectory file (.txt, .csv or .ndjson)")
        return [path]
    if path.exists() and not path.is_dir():
        raise DataError(f"{path}: not a regular file or a folder")
    found = path.iterdir() if path.is_dir() else map(Path, glob.glob(pattern))
    files = sorted(p for p in found if p.suffix in TRACK_SUFFIXES and p.is_file())
    if not files:
        raise DataError(f"{pattern}: no trajectory files (.txt, .csv or .ndjson) there")
    return files


def bundled_or_local(pattern: str) -> Path:
    """`pattern` as a path: itself, unless it is relative, does not exist, and names a file
    or folder of the bundled data."""
    path = Path(pattern)
    bundled = default_data_dir() / pattern
    return bundled if not path.is_absolute() and not path.exists() and bundled.exists() else path


def data_name(pattern: str) -> str:
    """The name that runs and labels give your own data: the file's or the folder's, with
    ':' and the characters paths cannot hold replaced by '-' (so that a run named after it
    is a work directory and a `DIR:MEMBER` model name)."""
    path = bundled_or_local(pattern)
    if path.is_file():
        name = path.stem
    else:
        folder = path if path.is_dir() else path.parent
        name = Path(os.path.abspath(folder)).name        # '.' and '..' name their folder
    # A leading '-' would read as a flag, a leading '.' hide the run's folder.
    return _UNSAFE_IN_NAMES.sub("-", name).lstrip("-.") or "data"


def has_validation(config: DataConfig) -> bool:
    return config.protocol in ("paper-val", "loo")


def load_split(config: DataConfig, split: str, grid: TimeGrid = TimeGrid()) -> WindowSet:
    """The windows of one split ('train', 'val', 'test' or 'all') of `config.scene`, cut to
    the time grid of the model that reads them."""
    _check(config, split)
    name = f"{config.scene}/{config.protocol}/{split}"
    per_file: list[tuple[Path, list[Window]]] = []
    for path in split_files(config, split):
        windows = _cut(path, config, grid)
        if config.protocol == "loo" or split == "all":
            per_file.append((path, kept(windows)))
        else:
            per_file.append((path, _temporal_split(windows, config, split)))
    return WindowSet(tuple(w for _, windows in per_file for w in windows), name,
                     tuple((str(path), len(windows)) for path, windows in per_file))


def split_frames(config: DataConfig, split: str, grid: TimeGrid = TimeGrid()
                 ) -> list[tuple[Tracks, int, int]]:
    """Each file's tracks on the model's grid with the frames (first, last) that the split's
    windows cover, for playing the split as a stream; files the split has no window of are
    left out."""
    _check(config, split)
    covered = []
    for path in split_files(config, split):
        windows = _cut(path, config, grid)
        chosen = (kept(windows) if config.protocol == "loo" or split == "all"
                  else _temporal_split(windows, config, split))
        if chosen:
            covered.append((_tracks(path, config, grid), min(w.frame_range[0] for w in chosen),
                            max(w.frame_range[1] for w in chosen)))
    return covered


def split_files(config: DataConfig, split: str) -> list[Path]:
    """The files of `config`'s scene (or own data) that `split` reads."""
    data_dir = Path(config.data_dir) if config.data_dir else default_data_dir()
    if config.data:
        return data_files(config.data)
    if config.protocol == "loo":
        return _loo_files(data_dir, config.scene, split)
    return scene_files(data_dir, config.scene)


def _check(config: DataConfig, split: str) -> None:
    if config.data and config.protocol == "loo":
        raise DataError("protocol 'loo' is defined for the bundled ETH/UCY scenes, not for "
                        "your own files; use 'paper' (a temporal 80/20 split of each file)")
    if config.scene not in SCENES and not config.data:
        raise DataError(f"unknown scene {config.scene!r}; choose one of {', '.join(SCENES)}")
    if config.protocol not in PROTOCOLS:
        raise DataError(f"unknown protocol {config.protocol!r}; choose one of "
                        f"{', '.join(PROTOCOLS)}")
    if split not in SPLITS:
        raise DataError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    if config.protocol == "loo" and config.scene not in ETH_UCY_SCENES:
        raise DataError(f"protocol 'loo' is defined for the ETH/UCY scenes "
                        f"({', '.join(ETH_UCY_SCENES)}), not {config.scene!r}")
    if split == "val" and not has_validation(config):
        raise DataError(f"protocol {config.protocol!r} has no validation split (the release "
                        "validates on its test windows); use protocol 'paper-val' or 'loo'")


@functools.lru_cache(maxsize=64)
def _cut(path: Path, config: DataConfig, grid: TimeGrid) -> tuple[Window | None, ...]:
    tracks = _tracks(path, config, grid)
    return tuple(cut_windows(tracks, grid.seq_len, grid.obs_len))


@functools.lru_cache(maxsize=64)
def _tracks(path: Path, config: DataConfig, grid: TimeGrid) -> Tracks:
    """A file's tracks on the model's grid, in metres, their speeds checked (refused or
    warned about once: the result is cached)."""
    tracks = read_tracks(path, drop_off_grid=config.drop_off_grid, columns=config.columns)
    frame_step, fps_assumed = tracks.frame_step, config.fps is None and tracks.rate_hz is None
    if config.data:
        frame_ids_per_s = config.fps or (tracks.rate_hz or grid.hz) * tracks.frame_step
        tracks = to_model_rate(tracks, config.fps, grid.hz, config.scale)
    else:
        # A bundled file is read at the rate it states (WILDTRACK's 2 Hz), else at the
        # 2.5 Hz of ETH/UCY's annotations; the paper's 0.4 s model reads those as they are.
        frame_ids_per_s = None
        rate = tracks.rate_hz or TimeGrid().hz
        if not math.isclose(rate, grid.hz):
            tracks = to_model_rate(tracks, rate * tracks.frame_step, grid.hz, own=False)
    check_speeds(tracks, grid.step_s, scale=config.scale if config.data else 1.0,
                 frame_ids_per_s=frame_ids_per_s, own=bool(config.data), frame_step=frame_step,
                 fps_assumed=fps_assumed)
    return tracks


def why_no_window(path: str | Path, config: DataConfig, split: str,
                  grid: TimeGrid = TimeGrid()) -> str:
    """Why file `path` gives `split` of `config` no window on `grid`: its longest track is
    shorter than a window, or its windows all go to other splits."""
    longest = longest_track(_tracks(Path(path), config, grid))
    if longest < grid.seq_len:
        return f"its longest track is {_steps(longest, grid)}; {_window_needs(grid)}"
    windows = len(kept(_cut(Path(path), config, grid)))
    return f"its {windows} window(s) all go to other splits ({_split_rule(config)})"


def no_windows_message(window_set: WindowSet, config: DataConfig, split: str,
                       grid: TimeGrid = TimeGrid()) -> str:
    """The one-line error for a `split` of `config` that has no window (`window_set`, as
    `load_split` returned it): its files, the steps a window needs and the longest track
    they hold, or the split rule that left them none."""
    paths = [path for path, _ in window_set.files]
    shown = ", ".join(paths[:3]) + (f" and {len(paths) - 3} more" if len(paths) > 3 else "")
    what = {"train": "training ", "val": "validation ", "test": "test ", "all": ""}[split]
    parts = [f"no {what}windows in {config.scene} ({config.protocol} protocol): none of "
             f"{shown or 'no files'} gives one"]
    longest = {path: longest_track(_tracks(Path(path), config, grid)) for path in paths}
    short = [path for path in paths if longest[path] < grid.seq_len]
    if long := [Path(path).name for path in paths if path not in short]:
        parts.append(f"the windows of {', '.join(long)} all go to other splits "
                     f"({_split_rule(config)})")
    if short:
        top = max(short, key=lambda path: longest[path])
        of = " of the others" if long else ""
        where = "" if len(paths) == 1 else f", in {Path(top).name}"
        parts.append(f"{_window_needs(grid)}, and the longest track{of} is "
                     f"{_steps(longest[top], grid)}{where}")
    return "; ".join(parts)


def _window_needs(grid: TimeGrid) -> str:
    return (f"a window needs someone detected at {_steps(grid.seq_len, grid, each=True)} in a "
            f"row ({grid.obs_len} observed, {grid.pred_len} predicted)")


def _steps(count: int, grid: TimeGrid, *, each: bool = False) -> str:
    """'10 steps (4 s)', each: '20 steps of 0.4 s (8 s)'; seconds as the paper counts them
    (its 8 observed steps of 0.4 s are 3.2 s)."""
    step = f" of {grid.step_s:g} s" if each else ""
    return f"{count} step{'s' if count != 1 else ''}{step} ({round(count * grid.step_s, 2):g} s)"


def _split_rule(config: DataConfig) -> str:
    rule = (f"{config.protocol}: each file's first {config.train_fraction:.0%} of windows "
            "train, the rest test")
    if config.protocol == "paper-val":
        rule += (f"; the last {config.val_fraction:.0%} of its train windows validate, and "
                 "train windows overlapping them are dropped")
    return rule


def _temporal_split(windows: tuple[Window | None, ...], config: DataConfig,
                    split: str) -> list[Window]:
    """Split one file's window starts in time (windows has num_windows + 1 entries)."""
    num_train = int(len(windows) * config.train_fraction)  # = int((num_windows + 1) * 0.8)
    if split == "test":
        return kept(windows[num_train:])
    if config.protocol == "paper":
        return kept(windows[:num_train])
    # paper-val: carve validation from the end of the train starts, then drop the train
    # windows whose time grid reaches the first validation frame.
    train_candidates = kept(windows[:num_train])
    num_val = max(1, round(len(train_candidates) * config.val_fraction))
    val = train_candidates[len(train_candidates) - num_val:]
    if split == "val":
        return val
    first_val_frame = min(w.frame_range[0] for w in val)
    return [w for w in train_candidates[:len(train_candidates) - num_val]
            if w.frame_range[1] < first_val_frame]


def _loo_files(data_dir: Path, scene: str, split: str) -> list[Path]:
    splits_path = data_dir / "eth_ucy" / "loo" / "splits.json"
    try:
        splits = json.loads(splits_path.read_text())
    except FileNotFoundError:
        raise DataError(f"{splits_path}: no such file") from None
    except json.JSONDecodeError as error:
        raise DataError(f"{splits_path}:{error.lineno}: not valid JSON ({error.msg})") from None
    try:
        names = splits[scene][split]
    except KeyError:
        raise DataError(f"{splits_path}: no {split!r} file list for scene {scene!r}") from None
    return [data_dir / "eth_ucy" / "loo" / "files" / name for name in names]
