"""Figures render from a (random, untrained) run directory, drawing the run's window, its
predictions and its records; nothing is drawn inside jit."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from matplotlib.colors import to_rgb

from gst_jax import data, figures, plot
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.io.workdir import WorkDir, run_config
from gst_jax.testing.drawn import colour_pixels, line_data, saved_figures
from gst_jax.training.state import create_train_state


@pytest.fixture(scope="module")
def random_run(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("run")
    model, data_config, train_config = ModelConfig(), DataConfig(scene="zara1"), TrainConfig()
    state = create_train_state(model, jax.random.key(0))
    checkpointer = WorkDir(workdir).checkpointer()
    checkpointer.save(1, state, run_config(model, data_config, train_config), [])
    checkpointer.close()
    (workdir / "metrics.jsonl").write_text("".join(
        json.dumps({"epoch": e, "loss": 2.0 / e, "val_aoe": 1.0 / e, "val_foe": 2.0 / e}) + "\n"
        for e in range(1, 4)))
    return workdir


WINDOW = 3          # of zara1's test split: 7 people, 4 of them fully detected, one seen
                    # only at the first 4 steps


def _observed_window() -> tuple[np.ndarray, np.ndarray]:
    """The positions (20, N, 2) of the window drawn, and where they exist (20, N)."""
    window = data.load_split(DataConfig(scene="zara1"), "test")[WINDOW]
    return window.positions, window.position_mask > 0


def test_the_scene_figure_draws_the_windows_paths_its_samples_and_graphs(random_run, tmp_path):
    """`plot scene`: the observed (blue) and true (green) paths are the window's own
    positions; each person the model predicts (seen at the last observed step) has its K = 2
    sampled paths and their mean over the 12 predicted steps, red where fully detected and
    orange where not; the graph panels place the people present where the window has them,
    beside an (N, N + 1) adjacency matrix; the PDF draws the same paths."""
    out = tmp_path / "scene.png"
    with saved_figures() as saved:
        plot.main(["scene", str(random_run), "--out", str(out), "--window", str(WINDOW),
                   "--samples", "2", "--pdf"])
    positions, seen = _observed_window()
    num = seen.shape[1]
    paths, graph, matrix = saved[out].axes[:3]
    observed = [positions[:8][seen[:8, i], i] for i in range(num) if seen[:8, i].any()]
    truth = [positions[8:][seen[8:, i], i] for i in range(num) if seen[8:, i].any()]
    for drawn, expected in ((line_data(paths, "tab:blue"), observed),
                            (line_data(paths, "tab:green"), truth)):
        assert len(drawn) == len(expected)
        for xy, path in zip(drawn, expected):
            np.testing.assert_array_equal(xy, path)
    fully = np.all(seen, axis=0)
    predicted = seen[7]
    for colour, people in (("tab:red", fully & predicted), ("tab:orange", ~fully & predicted)):
        lines = line_data(paths, colour)
        assert len(lines) == 3 * people.sum() > 0            # 2 samples and their mean each
        assert all(xy.shape == (12, 2) and np.isfinite(xy).all() for xy in lines)
    np.testing.assert_array_equal(graph.collections[0].get_offsets(), positions[7][seen[7]])
    assert matrix.images[0].get_array().shape == (num, num + 1)
    assert out.with_suffix(".pdf").read_bytes().startswith(b"%PDF")
    for drawn, again in zip(line_data(paths), line_data(saved[out.with_suffix(".pdf")].axes[0])):
        np.testing.assert_array_equal(drawn, again)
    assert colour_pixels(out) > 5_000        # its legend alone has 384 pixels in colour


def test_the_scene_figure_tells_sampled_edges_from_their_selection_probability(tmp_path):
    """Three people present and a fourth slot empty: 0 -> 1 sampled with selection
    probability 0 (a row of zeros: the noise's draw), 1 -> 2 with 0.7, 2 -> the ghost and to
    the empty slot (no arrow). The first is dashed pink, the second purple; the panel gives
    their mean selection probability, 0.35, and counts the edge to the empty slot; the caption
    says what the arrows are and are not."""
    adjacency, selection = np.zeros((4, 5)), np.zeros((4, 5))
    adjacency[0, 1] = adjacency[1, 2] = adjacency[2, 4] = adjacency[2, 3] = 1.0
    selection[1, 2], selection[2, 4] = 0.7, 1.0
    positions = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [5.0, 5.0]])
    present = np.array([True, True, True, False])
    out = tmp_path / "scene.png"
    with saved_figures() as saved:
        figures.scene_prediction(np.zeros((8, 4, 2)), np.ones((8, 4)), np.zeros((12, 4, 2)),
                                 np.ones((12, 4)), np.zeros((2, 12, 4, 2)), present, present,
                                 [(adjacency, selection, positions, np.zeros((4, 2)), present)],
                                 ["t = 8"], out)
    figure = saved[out]
    graph = figure.axes[1]
    arrows = {(tuple(a.xyann), tuple(a.xy)): a.arrow_patch for a in graph.texts}
    assert set(arrows) == {((0.0, 0.0), (1.0, 0.0)), ((1.0, 0.0), (1.0, 1.0))}
    by_noise, selected = arrows[(0.0, 0.0), (1.0, 0.0)], arrows[(1.0, 0.0), (1.0, 1.0)]
    assert by_noise.get_linestyle() == "--" and selected.get_linestyle() == "-"
    assert to_rgb(by_noise.get_edgecolor()) == to_rgb("tab:pink")
    assert to_rgb(selected.get_edgecolor()) == to_rgb("tab:purple")
    assert graph.get_title().splitlines()[1:] == [
        "selection probability of these edges: mean 0.35",
        "1 more sampled to empty slots (not drawn)"]
    assert [text.get_text() for text in figure.texts] == [figures.SAMPLED_EDGES_CAPTION]
    assert "not drawn here" in figures.SAMPLED_EDGES_CAPTION


def test_the_attention_figure_draws_every_neighbour_where_the_model_sees_it(random_run,
                                                                          tmp_path):
    """`plot attention --agent 1`: a line per other person and one for the ghost over the 19
    selector calls (8 observed, 11 predicted), probabilities; a neighbour has attention at a
    call exactly where the model sees it (detected at that observed step, or predicted: seen
    at the last observed one), so the person seen only at the first 4 steps has none after."""
    out = tmp_path / "attention.png"
    with saved_figures() as saved:
        plot.main(["attention", str(random_run), "--out", str(out), "--window", str(WINDOW),
                   "--agent", "1"])
    _, seen = _observed_window()
    visible = np.concatenate([seen[:8], np.repeat(seen[7:8], 11, axis=0)])      # (19, N)
    ax = saved[out].axes[0]
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert {label for label in lines if not label.startswith("_")} == {
        "ghost", *(f"pedestrian {j}" for j in range(seen.shape[1]) if j != 1)}
    for label, line in lines.items():
        if label.startswith("pedestrian"):
            calls, attention = line.get_xdata(), line.get_ydata()
            np.testing.assert_array_equal(calls, np.arange(1, 20))
            assert np.all((attention >= 0) & (attention <= 1))
            np.testing.assert_array_equal(attention > 0, visible[:, int(label.split()[1])])
    assert not visible[4:, 6].any() and visible[:4, 6].all()
    assert colour_pixels(out) > 600          # its legend alone has 442 pixels in colour


def test_the_training_figure_draws_the_recorded_loss_and_validation_errors(random_run,
                                                                         tmp_path):
    """`plot training`: the loss and the validation AOE and FOE of metrics.jsonl per epoch."""
    out = tmp_path / "training.png"
    with saved_figures() as saved:
        plot.main(["training", str(random_run), "--out", str(out)])
    loss, validation = saved[out].axes
    epochs = [1, 2, 3]
    [drawn] = line_data(loss)
    np.testing.assert_allclose(drawn, np.column_stack([epochs, [2.0, 1.0, 2 / 3]]))
    aoe, foe = line_data(validation)
    np.testing.assert_allclose(aoe, np.column_stack([epochs, [1.0, 0.5, 1 / 3]]))
    np.testing.assert_allclose(foe, np.column_stack([epochs, [2.0, 1.0, 2 / 3]]))
    assert colour_pixels(out) > 2_000        # its legend alone has 478 pixels in colour


def test_bad_window_is_a_clear_error(random_run):
    with pytest.raises(SystemExit, match="out of range"):
        plot.main(["scene", str(random_run), "--window", "100000"])
