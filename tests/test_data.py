"""The numpy data layer: readers, windowing, protocols, batching, make_batch, stats."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gst_jax import data
from gst_jax.config import CROWD_SCENES, ETH_UCY_SCENES, DataConfig, TimeGrid
from gst_jax.data.stats import split_stats
from gst_jax.data.windows import cut_windows
from gst_jax.errors import DataError

FIXTURES = Path(__file__).parent / "fixtures"


def _write(tmp_path: Path, text: str, name: str = "tracks.txt") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# --- readers -------------------------------------------------------------------------------

def test_text_reader_accepts_tabs_and_spaces(tmp_path):
    path = _write(tmp_path, "10\t1.0\t0.5\t1.5\n0 2 3.0 4.0\n\n0.0\t1\t0.0 1.0\n")
    tracks = data.read_tracks(path)
    np.testing.assert_array_equal(tracks.frames, [0, 0, 10])
    np.testing.assert_array_equal(tracks.pedestrians, [1, 2, 1])
    np.testing.assert_allclose(tracks.xy, [[0, 1], [3, 4], [0.5, 1.5]])
    assert tracks.frame_step == 10


@pytest.mark.parametrize("text, problem, line", [
    ("0 1 0.0 1.0\n10 1 abc 1.0\n", "x is not a number: 'abc'", 2),
    ("0 1 0.0 1.0\n10 1 1.0\n", "expected 4 columns", 2),
    ("0 1 0.0 1.0\n10 1 nan 1.0\n", "x is not finite", 2),
    ("0 1 0.0 1.0\n10 1 inf 1.0\n", "x is not finite", 2),
    ("0 1 0.0 1.0\n10 2 0.0 1.0\n0 1 5.0 5.0\n",
     "duplicate row for frame 0, pedestrian 1 (first at line 1)", 3),
    ("0 1.5 0.0 1.0\n", "pedestrian id is not an integer", 1),
])
def test_text_reader_rejects_bad_rows_naming_file_and_line(tmp_path, text, problem, line):
    path = _write(tmp_path, text)
    with pytest.raises(DataError) as error:
        data.read_tracks(path)
    assert f"{path}:{line}:" in str(error.value)
    assert problem in str(error.value)


def test_empty_file_is_an_error(tmp_path):
    path = _write(tmp_path, "\n  \n")
    with pytest.raises(DataError, match="empty file"):
        data.read_tracks(path)


def test_ndjson_reader_reads_frame_step_from_data(tmp_path):
    lines = ['{"scene": {"id": 0, "p": 1, "s": 0, "e": 10, "fps": 2, "tag": [1, []]}}']
    lines += [json.dumps({"track": {"f": f, "p": 1, "x": f / 10, "y": 0.0}}) for f in (0, 5, 10)]
    tracks = data.read_tracks(_write(tmp_path, "\n".join(lines), "crowd.ndjson"))
    assert tracks.frame_step == 5 and len(tracks.frames) == 3


@pytest.mark.parametrize("line, problem", [
    ('{"track": {"f": 0, "p": 1, "x": 0.0}}', "track record lacks y"),
    ('{"track": {"f": 0, "p": 1, "x": "a", "y": 0.0}}', "x is not a number"),
    ('{"track": {"f": 0, "p": 1, "x": NaN, "y": 0.0}}', "x is not finite"),
    ('{"track": ', "not valid JSON"),
    ('{"other": 1}', "expected a 'scene' or 'track' record"),
])
def test_ndjson_reader_rejects_bad_records(tmp_path, line, problem):
    good = '{"track": {"f": 0, "p": 2, "x": 0.0, "y": 0.0}}'
    path = _write(tmp_path, good + "\n" + line + "\n", "crowd.ndjson")
    with pytest.raises(DataError) as error:
        data.read_tracks(path)
    assert f"{path}:2:" in str(error.value) and problem in str(error.value)


def test_bundled_files_frame_steps():
    root = data.default_data_dir()
    assert data.read_tracks(root / "eth_ucy/raw/eth/biwi_eth.txt").frame_step == 10
    assert data.read_tracks(root / "trajnetpp/lcas.ndjson").frame_step == 1
    assert data.read_tracks(root / "trajnetpp/wildtrack.ndjson").frame_step == 5


# --- rates: a file's annotations on the model's steps ------------------------------------------

def test_a_2hz_file_is_interpolated_to_the_model_s_0_4s_steps(tmp_path):
    # Annotations every 5 frame ids at 10 per second (2 Hz, as WILDTRACK's): the model's
    # 0.4 s steps are frames 0, 4, 8, 12, 16, 20. Pedestrian 1 is seen at every annotation
    # (y bent, so that a wrong weight shows); 2 misses frame 10 (5 and 15 are 1 s apart,
    # more than 2 steps: no step between them); 3 is seen at 5 and 10 only.
    rows = [(f, 1, f / 10, (f / 5) ** 2) for f in (0, 5, 10, 15, 20)]
    rows += [(f, 2, 5.0, f / 10) for f in (0, 5, 15, 20)]
    rows += [(f, 3, -f / 10, 1.0) for f in (5, 10)]
    path = _write(tmp_path, "\n".join(" ".join(map(str, row)) for row in rows))
    tracks = data.readers.to_model_rate(data.read_tracks(path), 10, model_hz=2.5, scale=2.0)
    assert tracks.frame_step == 4 and tracks.rate_hz == 2.5
    found = {(int(f), int(p)): tuple(xy) for f, p, xy in
             zip(tracks.frames, tracks.pedestrians, tracks.xy)}
    expected = {(0, 1): (0.0, 0.0), (4, 1): (0.4, 0.8), (8, 1): (0.8, 2.8),
                (12, 1): (1.2, 6.0), (16, 1): (1.6, 10.4), (20, 1): (2.0, 16.0),
                (0, 2): (5.0, 0.0), (4, 2): (5.0, 0.4), (16, 2): (5.0, 1.6), (20, 2): (5.0, 2.0),
                (8, 3): (-0.8, 1.0)}
    assert found.keys() == expected.keys()
    for key, (x, y) in expected.items():
        np.testing.assert_allclose(found[key], (2 * x, 2 * y), atol=1e-12, err_msg=str(key))
    assert list(tracks.frames) == sorted(tracks.frames)


@pytest.mark.parametrize("fps, problem", [
    (3, "annotated at 3 Hz (a row every frame id at 3 per second), not a multiple of the "
        "model's 2.5 Hz, and its 0.4 s steps would fall between frame ids (1.2 apart); number "
        "its frames in finer units (frame ids x5, read with --fps 15)"),
    (1, "annotated at 1 Hz (a row every frame id at 1 per second), less than 1/2 of the "
        "model's 2.5 Hz: its rows are more than 2 steps of 0.4 s apart, too far apart to "
        "interpolate; check --fps, or train a model with --step 1"),
])
def test_rates_that_cannot_be_put_on_the_model_s_steps_are_refused(tmp_path, fps, problem):
    path = _write(tmp_path, "".join(f"{f} 1 {f / 10} 0.0\n" for f in range(30)))
    with pytest.raises(DataError) as error:
        data.readers.to_model_rate(data.read_tracks(path), fps, model_hz=2.5)
    assert str(error.value) == f"{path}: {problem}"


def _raw_speeds(path: Path, step_s: float) -> np.ndarray:
    """m/s between consecutive annotations of one pedestrian, one `step_s` apart, straight
    from the ndjson's track rows."""
    rows = sorted((r["track"]["p"], r["track"]["f"], r["track"]["x"], r["track"]["y"])
                  for r in map(json.loads, path.read_text().splitlines()) if "track" in r)
    table = np.array(rows, dtype=float)
    steps = np.diff(table[:, 1])
    same = (np.diff(table[:, 0]) == 0) & (steps == np.median(steps))
    return np.linalg.norm(np.diff(table[:, 2:], axis=0)[same], axis=1) / step_s


def test_wildtrack_is_read_at_its_own_2hz_by_scene_and_by_data():
    path = data.default_data_dir() / "trajnetpp" / "wildtrack.ndjson"
    scene = data.load_split(DataConfig(scene="wildtrack"), "train")
    own = data.load_split(DataConfig(scene="wildtrack", data=str(path)), "train")
    assert scene.stats() == own.stats() and len(scene) > 300
    assert {w.frame_step for w in scene.windows} == {4}       # 0.4 s at 10 frame ids a second
    for a, b in zip(scene.windows, own.windows):
        np.testing.assert_array_equal(a.positions, b.positions)
    # Its people walk at the speeds of its own 0.5 s rows: a window's steps are 0.4 s.
    tracks = data.protocols._tracks(path, DataConfig(scene="wildtrack"), TimeGrid())
    ours = data.checks.step_speeds(tracks, 0.4)
    raw = _raw_speeds(path, 0.5)
    assert np.median(ours) == pytest.approx(np.median(raw), rel=0.02)
    assert np.median(raw) < 0.9 < 1.0 < np.median(raw) * 0.5 / 0.4     # not 25 % fast


# Each bundled file's flags, as data/SOURCES.md gives them (the 4 Hz simulations are read by
# models with 0.25 s steps).
BUNDLED_FLAGS = {"crowd_10hz.txt": ["--fps", "10", "--units", "cm"],
                 "crowd_mot.csv": ["--fps", "10"],
                 "orca-humans20-seed101-episode0.txt": [
                     "--fps", "4", "--step", "0.25", "--obs-len", "5", "--pred-len", "5"],
                 "orca-reactive-humans20-shiftspeed-seed110-episode0.txt": [
                     "--fps", "4", "--step", "0.25", "--obs-len", "5", "--pred-len", "5"]}


def _bundled_files() -> list[Path]:
    root = data.default_data_dir()
    return sorted(path for path in root.rglob("*") if path.suffix in (".txt", ".csv", ".ndjson"))


@pytest.mark.parametrize("path", _bundled_files(), ids=lambda path: path.name)
def test_every_bundled_file_loads_through_data(path, capsys):
    from gst_jax.data.__main__ import main
    main(["stats", "--data", str(path), "--protocol", "paper", "--json",
          *BUNDLED_FLAGS.get(path.name, [])])
    counts = json.loads(capsys.readouterr().out)["scenes"][path.stem]
    assert sum(split["windows"] for split in counts.values()) > 0, counts


def test_the_4hz_simulations_on_0_4s_steps_are_refused_with_the_fix():
    from gst_jax.data.__main__ import main
    path = (data.default_data_dir() / "samples" / "crowdnav_orca"
            / "orca-humans20-seed101-episode0.txt")
    with pytest.raises(SystemExit) as error:
        main(["stats", "--data", str(path), "--fps", "4"])
    assert str(error.value) == (
        f"error: {path}: annotated at 4 Hz (a row every frame id at 4 per second), not a "
        "multiple of the model's 2.5 Hz, and its 0.4 s steps would fall between frame ids (1.6 "
        "apart); number its frames in finer units (frame ids x5, read with --fps 20)")


# --- windowing -------------------------------------------------------------------------------

def test_hand_built_windows(tmp_path):
    # Pedestrian 1 walks through frames 0..40; pedestrian 2 leaves after frame 10 and is
    # back at 30 (a gap); pedestrian 3 appears at frame 20.
    rows = [(f, 1, f / 10, 0.0) for f in range(0, 50, 10)]
    rows += [(0, 2, 0.0, 1.0), (10, 2, 0.0, 2.0), (30, 2, 0.0, 4.0)]
    rows += [(20, 3, 5.0, 5.0), (30, 3, 5.0, 6.0)]
    path = _write(tmp_path, "".join(f"{f} {p} {x} {y}\n" for f, p, x, y in rows))
    windows = cut_windows(data.read_tracks(path), seq_len=3, obs_len=2)
    # 5 frames -> num_windows = 3, the release enumerates starts 0..3; start 3 is too short.
    assert len(windows) == 4 and windows[3] is None
    first = windows[0]
    np.testing.assert_array_equal(first.pedestrian_ids, [1, 2, 3])
    np.testing.assert_array_equal(first.position_mask, [[1, 1, 0], [1, 1, 0], [1, 0, 1]])
    np.testing.assert_allclose(first.positions[:, 1], [[0, 1], [0, 2], [0, 0]])
    np.testing.assert_array_equal(first.fully_detected(), [True, False, False])
    node_mask = data.node_mask_from_positions(first.position_mask)
    np.testing.assert_array_equal(node_mask[:, 1], [1, 1, 0])
    np.testing.assert_array_equal(node_mask[:, 2], [0, 0, 0])  # no displacement yet
    second = windows[1]  # frames 10, 20, 30
    np.testing.assert_array_equal(second.position_mask[:, 1], [1, 0, 1])
    np.testing.assert_array_equal(data.node_mask_from_positions(second.position_mask)[:, 1],
                                  [1, 0, 0])


def test_windows_list_predicted_then_observed_then_unobserved_pedestrians(tmp_path):
    # Ids 1..4 over frames 0..30, observing the first two steps: 1 arrives after the
    # observation, 2 is seen at step 0 only, 3 and 4 are predicted (only 4 fully detected).
    rows = [(20, 1, 0.0, 0.0), (30, 1, 0.0, 1.0), (0, 2, 1.0, 0.0)]
    rows += [(f, 3, 2.0, f / 10) for f in range(0, 30, 10)]
    rows += [(f, 4, 3.0, f / 10) for f in range(0, 40, 10)]
    path = _write(tmp_path, "".join(f"{f} {p} {x} {y}\n" for f, p, x, y in rows))
    window = cut_windows(data.read_tracks(path), seq_len=4, obs_len=2)[0]
    np.testing.assert_array_equal(window.pedestrian_ids, [3, 4, 2, 1])
    assert (window.num_predicted, window.num_observed, window.num_pedestrians) == (2, 3, 4)
    np.testing.assert_allclose(window.positions[:, 0], [[2, 0], [2, 1], [2, 2], [0, 0]])
    batch = data.pad_windows([window], 8, predicted_slots=2, observed_only=True)
    assert batch.position_mask[0, :, :3].any(axis=0).all()
    assert not batch.position_mask[0, :, 3:].any()
    np.testing.assert_array_equal(batch.predicted_slots, [[1, 1]])
    with pytest.raises(ValueError, match="does not fit"):
        data.pad_windows([window], 8, predicted_slots=1)


def test_window_without_fully_detected_pedestrian_is_dropped(tmp_path):
    rows = [(0, 1, 0, 0), (10, 1, 1, 0), (10, 2, 0, 1), (20, 2, 1, 1)]
    path = _write(tmp_path, "".join(f"{f} {p} {x} {y}\n" for f, p, x, y in rows))
    assert cut_windows(data.read_tracks(path), seq_len=3, obs_len=2) == [None, None]


# --- protocols -------------------------------------------------------------------------------

def test_paper_protocol_reproduces_reference_counts():
    reference = json.loads((FIXTURES / "reference_windows.json").read_text())
    ours = split_stats(DataConfig(protocol="paper"), list(ETH_UCY_SCENES))
    assert ours["scenes"] == reference["scenes"]


def test_stats_command_json_matches_reference():
    reference = json.loads((FIXTURES / "reference_windows.json").read_text())
    result = subprocess.run([sys.executable, "-m", "gst_jax.data", "stats", "--protocol",
                             "paper", "--json"], capture_output=True, text=True, check=True)
    assert json.loads(result.stdout)["scenes"] == reference["scenes"]


def test_stats_command_table_shows_partial_share():
    result = subprocess.run([sys.executable, "-m", "gst_jax.data", "stats", "--scene", "zara1"],
                            capture_output=True, text=True, check=True)
    # zara1 train: 581 windows, 5627 slots, 1979 fully detected -> 64.8% partial.
    assert "581" in result.stdout and "64.8%" in result.stdout


def _frames(window):
    first, last = window.frame_range
    return set(range(first, last + 1, window.frame_step))


@pytest.mark.parametrize("scene", ["eth", "univ", "lcas"])
def test_validation_carve_out_has_no_temporal_overlap(scene):
    config = DataConfig(scene=scene, protocol="paper-val")
    train, val = data.load_split(config, "train"), data.load_split(config, "val")
    assert len(train) > 0 and len(val) > 0
    for source in {w.source for w in val.windows}:
        val_frames = set().union(*(_frames(w) for w in val.windows if w.source == source))
        for window in train.windows:
            if window.source == source:
                assert not (_frames(window) & val_frames)
    paper_test = data.load_split(DataConfig(scene=scene), "test")
    assert data.load_split(config, "test").stats() == paper_test.stats()
    assert len(train) + len(val) < len(data.load_split(DataConfig(scene=scene), "train"))


def test_loo_split_files():
    config = DataConfig(scene="eth", protocol="loo")
    test_sources = {Path(w.source).name for w in data.load_split(config, "test").windows}
    assert test_sources == {"biwi_eth.txt"}
    train_sources = {Path(w.source).name for w in data.load_split(config, "train").windows}
    assert "biwi_hotel_train.txt" in train_sources
    assert not any(name.startswith("biwi_eth") for name in train_sources)
    val_sources = {Path(w.source).name for w in data.load_split(config, "val").windows}
    assert val_sources and all(name.endswith("_val.txt") for name in val_sources)


@pytest.mark.parametrize("scene, step", [("lcas", 1), ("wildtrack", 4)])
def test_trajnet_scenes_window_on_their_own_frame_step(scene, step):
    train = data.load_split(DataConfig(scene=scene), "train")
    test = data.load_split(DataConfig(scene=scene), "test")
    assert len(train) > len(test) > 0
    assert {w.frame_step for w in train.windows} == {step}


@pytest.mark.parametrize("protocol, split", [("paper", "train"), ("paper", "test"),
                                             ("paper-val", "val")])
def test_crowd_is_every_scene_split_as_in_its_own_scene(protocol, split):
    crowd = data.load_split(DataConfig(scene="crowd", protocol=protocol), split)
    scenes = [data.load_split(DataConfig(scene=scene, protocol=protocol), split)
              for scene in CROWD_SCENES]
    assert crowd.files == tuple(file for scene in scenes for file in scene.files)
    def starts(windows):
        return [(w.source, w.start_frame) for w in windows]
    assert starts(crowd.windows) == starts(w for scene in scenes for w in scene.windows)


@pytest.mark.parametrize("config, split, problem", [
    (DataConfig(scene="crowd", protocol="loo"), "train", "protocol 'loo' is defined for"),
    (DataConfig(scene="atlantis"), "train", "unknown scene 'atlantis'"),
    (DataConfig(protocol="random"), "train", "unknown protocol 'random'"),
    (DataConfig(scene="lcas", protocol="loo"), "train", "protocol 'loo' is defined for"),
    (DataConfig(), "val", "has no validation split"),
    (DataConfig(), "dev", "unknown split 'dev'"),
])
def test_bad_requests_are_explained(config, split, problem):
    with pytest.raises(DataError, match=problem):
        data.load_split(config, split)


# --- batching --------------------------------------------------------------------------------

def test_padding_keeps_real_entries():
    windows = data.load_split(DataConfig(scene="zara1"), "test")
    small = data.pad_windows(windows.windows[:3], 16)
    large = data.pad_windows(windows.windows[:3], 40, batch_size=5)
    for name in ("positions", "position_mask", "node_mask"):
        np.testing.assert_array_equal(getattr(large, name)[:3, :, :16], getattr(small, name))
        assert not getattr(large, name)[:, :, 16:].any()
    np.testing.assert_array_equal(large.scene_mask, [1, 1, 1, 0, 0])
    np.testing.assert_array_equal(large.window_index, [0, 1, 2, -1, -1])


def _step_windows(step: data.PackedStep) -> list[int]:
    return [int(i) for b in step.micro_batches for i in b.window_index[b.scene_mask > 0]]


def test_training_steps_are_seeded_size_packed_and_cover_every_window():
    windows = data.load_split(DataConfig(scene="eth", protocol="loo"), "test")  # 3-42 people
    steps = list(data.training_batches(windows, batch_size=16, seed=3, epoch=1))
    seen = sorted(i for step in steps for i in _step_windows(step))
    assert seen == list(range(len(windows)))
    assert [s.num_scenes for s in steps] == [16] * (len(steps) - 1) + [len(windows) % 16 or 16]
    shapes = set()
    for step in steps:
        assert len(_step_windows(step)) == step.num_scenes
        for batch in step.micro_batches:
            b, _, n = batch.shape
            p = batch.predicted_slots.shape[1]
            shapes.add((b, n, p))
            chosen = [windows[i] for i in batch.window_index if i >= 0]
            observed = max(w.num_observed for w in chosen)
            predicted = max(w.num_predicted for w in chosen)
            # Padded to the bucket of the pedestrians seen while observing, the prediction to
            # that of the predicted ones, who sit first.
            assert n == data.bucket_size(observed, data.TRAINING_BUCKETS)
            assert p == min(data.bucket_size(predicted, data.TRAINING_BUCKETS), n)
            np.testing.assert_array_equal(batch.predicted_slots, batch.node_mask[:, 7, :p])
            assert not batch.node_mask[:, 7, p:].any()
            if b == 1:              # a large window, alone, in its own bucket
                assert observed > data.SHARED_MICRO_BATCH_MAX
            else:                   # the small windows together, padded to the largest
                assert b == 16 and observed <= data.SHARED_MICRO_BATCH_MAX
    assert any(b == 1 for b, _, _ in shapes) and any(b == 16 for b, _, _ in shapes)
    assert len(shapes) <= len(data.TRAINING_BUCKETS) ** 2 / 2    # a small, fixed set of programs
    again = list(data.training_batches(windows, batch_size=16, seed=3, epoch=1))
    other = list(data.training_batches(windows, batch_size=16, seed=3, epoch=2))
    assert [_step_windows(s) for s in steps] == [_step_windows(s) for s in again]
    assert _step_windows(steps[0]) != _step_windows(other[0])
    # On a GPU: the same steps, each one micro-batch padded to the set's largest window.
    largest = data.bucket_size(max(w.num_observed for w in windows.windows),
                               data.TRAINING_BUCKETS)
    one_batch = list(data.training_batches(windows, batch_size=16, seed=3, epoch=1,
                                           one_micro_batch=True))
    assert [sorted(_step_windows(s)) for s in one_batch] == [sorted(_step_windows(s))
                                                              for s in steps]
    assert {b.shape[::2] + b.predicted_slots.shape[1:] for s in one_batch
            for b in s.micro_batches} == {(16, largest, largest)}


def test_evaluation_batches_respect_the_edge_budget():
    windows = data.load_split(DataConfig(scene="univ"), "test")
    budget = 8192
    batches = list(data.evaluation_batches(windows, edge_budget=budget))
    seen = np.concatenate([b.window_index[b.scene_mask > 0] for b in batches])
    assert sorted(seen.tolist()) == list(range(len(windows)))
    for batch in batches:
        b, _, n = batch.shape
        assert n in data.BUCKETS and (b * n * n <= budget or b == 1)
        for i in batch.window_index[batch.window_index >= 0]:
            assert data.bucket_size(windows[i].num_pedestrians) == n
            assert windows[i].num_predicted <= batch.predicted_slots.shape[1] <= n
    assert len({b.shape[2] for b in batches}) > 1


def test_a_bucket_of_few_windows_is_padded_to_the_next_power_of_two_of_them():
    """A validation split of three windows is predicted in a batch of 4 scenes, not of the
    budget's 256 (4.4 s against 0.09 s); a bucket of many windows keeps the budget's size."""
    from gst_jax.data.batching import EDGE_BUDGET

    hotel = data.load_split(DataConfig(scene="hotel"), "test")
    for count in (1, 3, 5):
        batches = list(data.evaluation_batches(hotel.subset(range(count))))
        assert sum(int(b.scene_mask.sum()) for b in batches) == count
        for batch in batches:
            real = int(batch.scene_mask.sum())
            assert batch.shape[0] == 1 << (real - 1).bit_length()
    univ = list(data.evaluation_batches(data.load_split(DataConfig(scene="univ"), "test")))
    assert max(b.shape[0] for b in univ if b.shape[2] == 48) == EDGE_BUDGET // 48 ** 2 == 7


# --- make_batch ------------------------------------------------------------------------------

def test_make_batch_from_nan_marked_observations():
    xy = np.zeros((2, 8, 3, 2))
    xy[..., 0] = np.arange(8)[None, :, None]
    xy[0, :5, 2] = np.nan          # pedestrian 2 appears at step 5
    xy[1, 7, 1] = np.nan           # pedestrian 1 lost at the last step
    assert data.make_batch(xy, pad_to_bucket=False).shape == (2, 8, 3)
    batch = data.make_batch(xy)
    assert batch.shape == (2, 8, 8)                      # padded to the smallest bucket
    np.testing.assert_array_equal(batch.position_mask[:, :, 3:], 0)
    np.testing.assert_array_equal(batch.positions[:, :, 3:], 0)
    np.testing.assert_array_equal(batch.position_mask[0, :, 2], [0] * 5 + [1] * 3)
    np.testing.assert_array_equal(batch.node_mask[0, :, 2], [0] * 6 + [1] * 2)
    assert batch.positions[0, 0, 2].tolist() == [0, 0]
    assert batch.node_mask[1, 7, 1] == 0 and batch.node_mask[1, 6, 1] == 1
    np.testing.assert_array_equal(batch.scene_mask, [1, 1])


@pytest.mark.parametrize("xy, problem", [
    (np.zeros((8, 3, 2)), r"shape \(B, T_obs, N, 2\)"),
    (np.zeros((1, 8, 3, 3)), r"shape \(B, T_obs, N, 2\)"),
    (np.full((2, 8, 3, 2), np.nan), r"scene\(s\) \[0, 1\] have no detected pedestrian"),
    (np.array([[[[np.nan, 1.0]]] * 8]), "one NaN coordinate"),
    (np.zeros((1, 0, 3, 2)), "empty axis"),
])
def test_make_batch_errors(xy, problem):
    with pytest.raises(ValueError, match=problem):
        data.make_batch(xy)


def test_data_layer_never_imports_jax():
    package = Path(data.__file__).parent
    for path in package.glob("*.py"):
        text = path.read_text()
        assert "import jax" not in text and "from jax" not in text, path
