"""A navigate episode's GIF is written whole or not at all (issue 94): an interrupt during the
write once left a 0-byte GIF under the name a rerun looks for."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from gst_jax.simulate.crowdnav.figures import animate_navigation

STEPS = 3


def _episode(path):
    robot = np.stack([np.linspace(0.0, 3.0, STEPS + 2), np.zeros(STEPS + 2)], axis=1)
    humans = np.zeros((STEPS + 2, 2, 2)) + np.array([[2.0, 2.0], [-2.0, 1.0]])
    return animate_navigation(robot, humans, np.array([4.0, 0.0]), STEPS, path, "episode 0")


def test_a_gif_holds_a_frame_per_step_and_nothing_is_left_beside_it(tmp_path):
    path = _episode(tmp_path / "run-episode0.gif")
    with Image.open(path) as gif:
        assert (gif.format, gif.n_frames) == ("GIF", STEPS + 1)
    assert [p.name for p in tmp_path.iterdir()] == ["run-episode0.gif"]


def test_an_interrupted_write_leaves_no_gif_and_keeps_the_last_whole_one(tmp_path, monkeypatch):
    def interrupted(image, fp, filename):        # Pillow's GIF writer, stopped part-way
        fp.write(b"GIF89a")
        raise KeyboardInterrupt

    path = tmp_path / "run-episode0.gif"
    monkeypatch.setitem(Image.SAVE_ALL, "GIF", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _episode(path)
    assert list(tmp_path.iterdir()) == []

    monkeypatch.undo()
    whole = _episode(path).read_bytes()
    monkeypatch.setitem(Image.SAVE_ALL, "GIF", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _episode(path)
    assert [p.name for p in tmp_path.iterdir()] == ["run-episode0.gif"]
    assert path.read_bytes() == whole
