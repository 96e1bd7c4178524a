"""What a figure draws, for tests that check a figure by more than the size of its file.

    saved_figures()       the matplotlib Figures saved inside a block, by the path each was
                          saved to: their axes' lines, points, bars and images stay readable
    line_data(ax)         the (n, 2) data of each line an axes draws
    bar_heights(ax)       the heights of each group of bars an axes draws
    bar_intervals(ax)     the (low, high) ends of the error bars of each group of bars
    errorbar_data(ax)     the points and error half-widths of each labelled errorbar series
    colour_pixels(image)  how many pixels of a PNG (or an RGB array) are in colour
    pixels_near(image, colour)
                          how many are of one colour (a matplotlib colour name)
    gif_frames(path)      a GIF's frames as RGB arrays

The package draws data in colour and axes, ticks, text, grids and reference lines in black
and grey, so a figure with empty axes has no pixel in colour at all: counting them tells a
drawn figure from an empty one where the Figure itself cannot be had (a command run as a
process). A legend's handles are in colour too, so a count is held to more than what the
legend alone draws.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator

import numpy as np
from matplotlib.colors import to_rgb
from matplotlib.container import BarContainer, ErrorbarContainer
from matplotlib.figure import Figure

# A pixel is in colour where its channels differ by more than this (0-1): black, white and
# every grey (text, grids at alpha 0.3, antialiased edges of either) differ by 0.
CHROMA = 0.2


@contextlib.contextmanager
def saved_figures() -> Iterator[dict[Path, Figure]]:
    """Every Figure saved to a file (`Figure.savefig` with a path) inside the block, by that
    path as given: closing it after the save keeps its artists."""
    saved: dict[Path, Figure] = {}
    original = Figure.savefig

    def recording(self, fname, *args, **kwargs):
        if isinstance(fname, (str, os.PathLike)):
            saved[Path(fname)] = self
        return original(self, fname, *args, **kwargs)

    # Patching the method is the point (mypy refuses assigning to one).
    Figure.savefig = recording  # type: ignore[method-assign]
    try:
        yield saved
    finally:
        Figure.savefig = original  # type: ignore[method-assign]


def line_data(ax, color=None) -> list[np.ndarray]:
    """The (n, 2) data of each line `ax` draws (of colour `color` only, if given), in the
    order drawn; lines without points left out."""
    lines = [line for line in ax.get_lines()
             if color is None or np.allclose(to_rgb(line.get_color()), to_rgb(color))]
    data = [np.asarray(line.get_xydata(), dtype=float) for line in lines]
    return [xy for xy in data if len(xy)]


def bar_heights(ax) -> list[np.ndarray]:
    """The heights of each group of bars `ax` draws (one `ax.bar` call each), in order."""
    return [np.array([bar.get_height() for bar in container], dtype=float)
            for container in ax.containers if isinstance(container, BarContainer)]


def bar_intervals(ax) -> list[np.ndarray]:
    """The (n, 2) low and high ends of the vertical error bars of each group of bars `ax`
    draws (`ax.bar(..., yerr=...)`), in order; groups without error bars left out."""
    intervals = []
    for container in ax.containers:
        if isinstance(container, BarContainer) and container.errorbar is not None:
            _, _, (bars, *_) = container.errorbar.lines
            intervals.append(np.array([sorted(np.asarray(segment, dtype=float)[:, 1])
                                       for segment in bars.get_segments()]))
    return intervals


def errorbar_data(ax) -> dict[str | None, tuple[np.ndarray, np.ndarray]]:
    """Each labelled `ax.errorbar` series of `ax`: its (n, 2) points and the half-heights
    (n,) of its vertical error bars."""
    series = {}
    for container in ax.containers:
        if isinstance(container, ErrorbarContainer):
            line, _, (bars, *_) = container.lines
            segments = [np.asarray(segment, dtype=float) for segment in bars.get_segments()]
            series[container.get_label()] = (
                np.asarray(line.get_xydata(), dtype=float),
                np.array([abs(s[1, 1] - s[0, 1]) / 2 for s in segments]))
    return series


def _rgb(image) -> np.ndarray:
    if isinstance(image, (str, os.PathLike)):
        import matplotlib.image
        image = matplotlib.image.imread(os.fspath(image))
    image = np.asarray(image)
    if image.dtype == np.uint8:
        image = image / 255.0
    return image[..., :3]


def colour_pixels(image) -> int:
    """How many pixels of `image` (a PNG's path or an (H, W, 3 or 4) array) are in colour."""
    rgb = _rgb(image)
    return int(((rgb.max(axis=-1) - rgb.min(axis=-1)) > CHROMA).sum())


def pixels_near(image, colour: str, tolerance: float = 0.08) -> int:
    """How many pixels of `image` are `colour` ('tab:blue'), each channel within
    `tolerance`: a line's core, not its antialiased edge or what a transparent one covers."""
    rgb = _rgb(image)
    return int((np.abs(rgb - np.array(to_rgb(colour))) <= tolerance).all(axis=-1).sum())


def gif_frames(path: str | os.PathLike) -> list[np.ndarray]:
    """The frames of a GIF as (H, W, 3) uint8 RGB arrays."""
    from PIL import Image, ImageSequence
    with Image.open(path) as gif:
        return [np.asarray(frame.convert("RGB")) for frame in ImageSequence.Iterator(gif)]
