"""The streaming predictor: a recorded scene replayed frame by frame predicts what the
window-based `predict` does on the same windows; slots are reused, capacity grows, a track that
appears is partially detected, bad frames are refused in one line; the pure step vmaps over
robots. A robot's loop: nothing compiles after warm_up, compiled programs outlive the process,
a recycled or forgotten id starts a new track whose predecessor's scores are dropped, NaN
detections read as missed (frame times: tests/test_stream_timing.py)."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gst_jax import conformal, coverage, data, resources, stream, stream_programs
from gst_jax.compiles import count_compiles
from gst_jax.data.readers import read_tracks, to_model_rate
from gst_jax.data.windows import cut_windows, kept
from gst_jax.errors import DataError
from gst_jax.predict import make_predict
from gst_jax.predictors import ConstantVelocity
from gst_jax.runs import load_model
from gst_jax.testing.drawn import line_data, saved_figures

# An episode of the navigation task's own humans (20 ORCA humans, what its robot detected).
SIM = (Path(__file__).parents[1] / "data" / "samples" / "crowdnav_orca"
       / "orca-humans20-seed101-episode0.txt")


def frames_of(tracks) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(frame id, ids, positions) of every step of a file's grid, empty steps included."""
    return list(coverage.frames(tracks, tracks.frames.min(), tracks.frames.max()))


def replay(run, tracks, **options) -> dict[int, stream.StreamOutput]:
    """The stream's output after each frame, by frame id, every frame the model's (a recording
    replayed waits for the model: `deadline_s=None`)."""
    player = stream.Stream(run, deadline_s=None, **options)
    return {f: player.step(ids, xy) for f, ids, xy in frames_of(tracks)}


def window_prediction(run, window, **options) -> dict[int, np.ndarray]:
    """{pedestrian id: (P, 2) mean future} of one window, as `evaluate` predicts it (the
    window's frame of coordinates, its origin added back)."""
    batch = next(data.evaluation_batches(data.WindowSet((window,))))
    prediction = make_predict(run.model_config, 1, with_graph=False, mean=True, **options)(
        run.params, jax.random.key(0), batch)
    positions = np.asarray(prediction.positions)[0, 0]                         # (P, N, 2)
    return {int(window.pedestrian_ids[k]): positions[:, k] + window.origin
            for k in range(window.num_predicted)}


def test_a_replayed_scene_predicts_what_its_windows_predict():
    """CrowdNav++'s configuration trained here (no edge selector, GST (P) in mean mode): a
    deterministic model, so each person's future must match whatever slot holds them."""
    run = load_model("pretrained:crowdnav_sim")
    grid = run.model_config.grid
    tracks = to_model_rate(read_tracks(SIM), 4.0, grid.hz)
    outputs = replay(run, tracks)
    windows = kept(cut_windows(tracks, grid.seq_len, grid.obs_len))
    compared = 0
    for window in windows[::7]:
        last_observed = window.start_frame + (grid.obs_len - 1) * window.frame_step
        out = outputs[last_observed]
        streamed = dict(zip(out.ids.tolist(), out.futures))
        expected = window_prediction(run, window)
        assert sorted(streamed) == sorted(expected)
        for pedestrian, future in expected.items():
            # float32 through other paddings and slot orders: rounding of metres-sized sums.
            np.testing.assert_allclose(streamed[pedestrian], future, rtol=0, atol=2e-5)
            compared += 1
    assert compared > 50


def test_the_paper_model_streams_the_windows_observations_exactly():
    """The paper's model samples its graph, with draws keyed by slot, so the stream and a
    window predict alike once laid out alike: the stream's history is exactly the window's
    observation, and it predicts the same people."""
    run = load_model("pretrained:eth_d")
    grid = run.model_config.grid
    [path] = data.protocols.scene_files(data.default_data_dir(), "eth")
    tracks = read_tracks(path)
    windows = {w.start_frame: w for w in kept(cut_windows(tracks, grid.seq_len, grid.obs_len))}
    player = stream.Stream(run, capacity=16, max_speed=None)     # ETH's walkers exceed 2.5 m/s
    checked = 0
    for f, ids, xy in frames_of(tracks)[:400]:
        out = player.step(ids, xy)
        window = windows.get(f - (grid.obs_len - 1) * tracks.frame_step)
        if window is None or checked >= 6:
            continue
        state = player.state
        slots = {int(i): k for k, i in enumerate(np.asarray(state.track_ids)) if i >= 0}
        observed = window.position_mask[:grid.obs_len].any(axis=0)
        for k in np.flatnonzero(observed):
            slot = slots[int(window.pedestrian_ids[k])]
            mask = window.position_mask[:grid.obs_len, k]
            np.testing.assert_array_equal(np.asarray(state.detected[slot]), mask)
            np.testing.assert_allclose(
                np.asarray(state.positions[slot])[mask > 0],
                (window.positions[:grid.obs_len, k] + window.origin)[mask > 0], atol=1e-4)
        assert sorted(out.ids.tolist()) == sorted(
            int(i) for i in window.pedestrian_ids[:window.num_predicted])
        checked += 1
    assert checked == 6


def test_slots_are_reused_a_new_track_is_partial_and_capacity_grows():
    run = load_model("pretrained:crowdnav_sim")
    player = stream.Stream(run, capacity=8)
    for t in range(3):
        out = player.step([5, 9], [[0.25 * t, 0.0], [1.0, 0.3 * t]])
    assert sorted(out.ids.tolist()) == [5, 9] and out.futures.shape == (2, 5, 2)
    out = player.step([5, 9, 40], [[0.75, 0.0], [1.0, 0.9], [3.0, 3.0]])
    state = player.state
    slot = int(np.flatnonzero(np.asarray(state.track_ids) == 40)[0])
    np.testing.assert_array_equal(np.asarray(state.detected[slot]), [0, 0, 0, 0, 1])
    assert 40 not in out.ids                # seen once: no displacement yet, not predicted
    for t in range(5):                      # 9 and 40 vanish; 5 walks on
        player.step([5], [[1.0 + 0.25 * t, 0.0]])
    assert sorted(i for i in np.asarray(player.state.track_ids).tolist() if i >= 0) == [5]
    crowd = np.arange(30)
    out = player.step(crowd, np.stack([crowd * 0.5, crowd * 0.0], 1))
    assert player.state.capacity == 32 and int(player.state.dropped) == 0
    assert sorted(np.asarray(player.state.track_ids).tolist())[-30:] == list(range(30))


def test_bad_frames_are_refused_in_one_line():
    player = stream.Stream(load_model("pretrained:crowdnav_sim"))
    with pytest.raises(DataError, match="track id 3 appears twice in one frame"):
        player.step([3, 3], [[0, 0], [1, 1]])
    with pytest.raises(DataError, match=r"track 7's position is \[nan, 0.0\]: not finite"):
        player.step([7], [[np.nan, 0]])
    with pytest.raises(DataError, match="track ids must be integers from 0"):
        player.step([-2], [[0, 0]])
    # Ragged lists were numpy's ValueError with a traceback (issue 94).
    with pytest.raises(DataError, match=r"^a frame's positions must be an array, got list"):
        player.step([1, 2], [[0, 0], [1]])
    with pytest.raises(DataError, match=r"^forget: track ids must be an array, got list"):
        player.forget([[1, 2], [3]])


def test_a_streams_arguments_of_the_wrong_kind_are_refused_in_one_line(sim_run):
    """Each was an AttributeError, a ValueError from deeper down, or accepted (issue 94)."""
    for make, problem in [
            (lambda: stream.Stream("pretrained:crowdnav_sim"),
             r"^Stream: run must be a loaded model .* got str 'pretrained:crowdnav_sim'$"),
            (lambda: stream.Stream(sim_run, regions="dtaci"),
             r"^Stream: regions must be gst_jax.conformal.Regions .* got str 'dtaci'$"),
            (lambda: stream.Stream(sim_run, non_finite=np.array(["raise"])),
             r"^Stream: non_finite must be one of \('raise', 'undetected'\), got array"),
            (lambda: stream.Stream(sim_run, convention="bogus"),
             r"^convention must be 'gst' or 'crowdnav', got 'bogus'$"),
            (lambda: stream.Stream(sim_run, convention="crowdnav", num_samples=20, mean=False),
             r"^CrowdNav\+\+'s predictor predicts the mean only")]:
        with pytest.raises(DataError, match=problem):
            make()


def test_the_pure_step_vmaps_over_robots():
    run = load_model("pretrained:crowdnav_sim")
    model = stream.StreamModel(run.model_config)
    step = jax.jit(jax.vmap(stream.make_step(model), in_axes=(None, 0, 0, 0)))
    robots, capacity = 3, 8
    state = jax.vmap(lambda _: stream.init_state(capacity, run.model_config.obs_len))(
        jnp.arange(robots))
    keys = jax.random.split(jax.random.key(0), robots)
    for t in range(4):
        ids = jnp.tile(jnp.array([1, 2, stream.FREE, stream.FREE]), (robots, 1))
        xy = jnp.stack([jnp.array([[0.3 * t, r], [r, 0.2 * t], [0, 0], [0, 0]], jnp.float32)
                        for r in range(robots)])
        state, futures, predicted, _, _ = step(run.params, state, stream.Frame(ids, xy), keys)
    assert futures.shape == (robots, 1, 5, capacity, 2)
    single = stream.Stream(run)
    for t in range(4):
        out = single.step([1, 2], [[0.3 * t, 2.0], [2.0, 0.2 * t]])
    np.testing.assert_allclose(np.asarray(futures[2, 0, :, :2]).swapaxes(0, 1), out.futures,
                               atol=1e-5)


@pytest.mark.parametrize("method, pooled", [("dtaci", True), ("aci", True), ("dtaci", False)])
def test_regions_are_issued_with_the_predictions_and_scored_k_steps_later(method, pooled):
    run = load_model("pretrained:crowdnav_sim")
    grid = run.model_config.grid
    tracks = to_model_rate(read_tracks(SIM), 4.0, grid.hz)
    regions = conformal.Regions(method, alpha=0.1, pooled=pooled)
    player = stream.Stream(run, regions=regions, deadline_s=None)     # every frame the model's
    covered = scored = 0
    issued_before = {}
    for t, (_, ids, xy) in enumerate(frames_of(tracks)):
        out = player.step(ids, xy)
        assert out.radii.shape == (len(out.ids), grid.pred_len)
        assert np.all(out.radii >= 0)
        if pooled and len(out.ids):         # pooled: one radius per horizon step for everyone
            np.testing.assert_array_equal(out.radii, np.broadcast_to(out.radii[0],
                                                                     out.radii.shape))
        delayed = out.delayed
        # The horizon-k score of the person in track slot s belongs to the prediction made
        # for that person k steps ago, with the radius issued then (by id: the stream moves
        # tracks to other slots when it shrinks, as new ids come and old ones are forgotten).
        slot_ids = np.asarray(player.state.track_ids)
        for slot, k in zip(*np.nonzero(delayed.mask)):
            assert delayed.issued[slot, k] == issued_before[t - k - 1][slot_ids[slot]][k]
        issued = np.asarray(player.state.feed.issued[t % grid.pred_len])
        issued_before[t] = {person: issued[slot] for slot, person in enumerate(slot_ids)}
        covered += int(np.sum(delayed.mask & (delayed.scores <= delayed.issued)))
        scored += int(np.sum(delayed.mask))
    assert scored > 1000
    assert 0.8 < covered / scored < 0.97, covered / scored


@pytest.mark.parametrize("method, pooled, options", [("aci", True, ()),
                                                     ("dtaci", False, (("output", "mean"),))])
def test_measuring_a_recording_gives_what_a_stream_with_regions_issues(method, pooled,
                                                                        options):
    """coverage.measure feeds a recording's scores to the method as they came back: the
    coverage and radii of a stream that issued the regions itself, to float rounding."""
    run = load_model("pretrained:crowdnav_sim")
    tracks = to_model_rate(read_tracks(SIM), 4.0, run.model_config.grid.hz)
    frames = frames_of(tracks)[:80]
    regions = conformal.Regions(method, 0.1, pooled, options)
    player = stream.Stream(run, regions=regions, capacity=coverage.live_tracks(frames, 8),
                           deadline_s=None)
    delayed = [player.step(ids, xy).delayed for _, ids, xy in frames]
    recording = coverage.record(run, [iter(frames)], calibration=0.25)
    result, _ = coverage.measure(recording, method, 0.1, pooled, options)
    after = delayed[recording.calibrating:]
    mask = np.stack([d.mask for d in after])
    covered = np.sum(mask & (np.stack([d.scores for d in after]) <=
                             np.stack([d.issued for d in after])), axis=(0, 1))
    radius = np.sum(np.where(mask, np.stack([d.issued for d in after]), 0), axis=(0, 1))
    assert result["scores"] == np.sum(mask, axis=(0, 1)).tolist() and min(result["scores"]) > 50
    np.testing.assert_allclose(result["coverage"], covered / np.sum(mask, axis=(0, 1)))
    np.testing.assert_allclose(result["radius"], radius / np.sum(mask, axis=(0, 1)), rtol=1e-5)


def test_the_conformal_command_reports_coverage_and_radius_per_horizon_step(tmp_path, capsys):
    """`python -m gst_jax.conformal` on the simulated crowd: JSON with coverage and radius
    per predicted step, split calibrated on the first 30 % of frames, and the figure: its
    coverage and mean radius are the result's, its scene draws the discs."""
    from matplotlib.patches import Circle

    from gst_jax.conformal.__main__ import main

    argv = ["pretrained:crowdnav_sim", "--data", str(SIM), "--fps", "4", "--split", "all",
            "--max-frames", "60"]
    results = {}
    for method in ("split", "dtaci"):
        figure = tmp_path / f"{method}.png"
        with saved_figures() as saved:
            main([*argv, "--method", method, "--json", "--figure", str(figure)])
        results[method] = result = json.loads(capsys.readouterr().out)
        assert figure.is_file() and list(saved) == [figure]
        axes = {ax.get_ylabel(): ax for ax in saved[figure].axes}
        seconds = result["step_s"] * np.arange(1, len(result["coverage"]) + 1)
        [coverage_line] = line_data(axes["long-run coverage"], "tab:purple")
        np.testing.assert_allclose(coverage_line, np.column_stack([seconds, result["coverage"]]))
        [radius_line] = line_data(axes["mean radius (m)"])
        np.testing.assert_allclose(radius_line, np.column_stack([seconds, result["radius"]]))
        discs = [p for p in axes["y (m)"].patches if isinstance(p, Circle)]
        assert discs and all(0 < disc.radius < 5 for disc in discs), len(discs)
    for result in results.values():
        assert result["frames"] == 60 and result["calibration_frames"] == 18
        assert len(result["coverage"]) == len(result["radius"]) == 5
        assert all(0.5 < c <= 1 for c in result["coverage"])
        assert all(0 < r < 5 for r in result["radius"])
        assert result["scores"][0] > result["scores"][-1] > 0    # step k is scored k steps later
        assert 0 < result["joint_coverage"] <= min(result["coverage"])
        assert result["joint_predictions"] > 0
    assert results["split"]["split_calibration_scores"] > 0
    assert results["split"]["bound"] is None and results["dtaci"]["bound"] is None
    main([*argv, "--method", "aci", "--max-frames", "30"])
    table = capsys.readouterr().out
    assert "coverage  radius (m)  scores (T)     bound" in table
    assert table.count("\n") == 2 + 5 + 1 and "steps inside their discs" in table
    main([*argv, "--method", "aci", "--json"])
    result = json.loads(capsys.readouterr().out)
    # Gibbs & Candes with the delay, per step: (1 + gamma + k C gamma) / (gamma T).
    assert result["gamma"] == 0.005 and len(result["bound"]) == 5
    assert all(b > 0 for b in result["bound"])


def test_whole_horizon_coverage_counts_a_prediction_only_with_every_step_inside():
    """One track, two steps, radius 1 everywhere: the prediction of frame 0 lands inside at
    both steps, frame 1's misses its second, frame 2's second step was never observed."""
    scores = np.zeros((5, 1, 2))
    mask = np.ones((5, 1, 2), bool)
    scores[1, 0, 0], scores[2, 0, 1] = 0.5, 0.5          # frame 0's steps 1, 2
    scores[2, 0, 0], scores[3, 0, 1] = 0.5, 2.0          # frame 1's
    scores[3, 0, 0], mask[4, 0, 1] = 0.5, False          # frame 2's
    files = [(scores, mask, np.zeros((5, 1), bool))]
    issued = list(np.ones((5, 1, 2)))
    assert coverage.joint_coverage(files, issued, calibrating=0) == {
        "joint_coverage": 0.5, "joint_predictions": 2}
    assert coverage.joint_coverage(files, issued, calibrating=1) == {
        "joint_coverage": 0.0, "joint_predictions": 1}


def test_the_shifted_crowd_of_the_coverage_study_steps_twice_as_far_halfway():
    """experiments/conformal_coverage.py's speed shift: every step of the task's humans for
    the first third, every second step after, as many frames: each person seen in two
    consecutive frames moves twice as far between them from halfway on."""
    from conformal_coverage import speed_doubling_crowd

    frames = speed_doubling_crowd(duration_s=30.0)            # 121 steps of the environment
    steps = np.diff([frame for frame, _, _ in frames])
    assert len(frames) == 81 and list(steps[:39]) == [1] * 39 and set(steps[40:]) == {2}
    assert all(len(set(ids.tolist())) == len(ids) for _, ids, _ in frames)

    def moved(a, b):        # the distance each person seen in frames a and b walked between
        _, here, there = np.intersect1d(a[1], b[1], return_indices=True)
        return np.linalg.norm(b[2][there] - a[2][here], axis=-1)
    before = np.concatenate([moved(frames[i], frames[i + 1]) for i in range(39)])
    after = np.concatenate([moved(frames[i], frames[i + 1]) for i in range(40, 80)])
    assert 1.8 < np.median(after) / np.median(before) < 2.2


# --- A robot's loop: no compiling once warmed up, one track per person, frames in time ----------


@pytest.fixture(scope="module")
def sim_run():
    return load_model("pretrained:crowdnav_sim")


def walkers(count: int, steps: int, step_s: float = 0.25) -> np.ndarray:
    """(steps, count, 2) straight walks at up to 1.4 m/s from points of a 12 m square."""
    rng = np.random.default_rng(3)
    start, velocity = rng.uniform(-6, 6, (count, 2)), rng.uniform(-1, 1, (count, 2))
    return start + velocity * step_s * np.arange(steps)[:, None, None]


def slot_of(player: stream.Stream, track: int) -> int:
    return int(np.flatnonzero(np.asarray(player.state.track_ids) == track)[0])


def test_after_warm_up_a_growing_crowd_compiles_nothing(sim_run):
    """Every compilation is counted, a program loaded from the persistent cache included:
    after warm_up(20), a crowd growing from 2 to 20 people (capacity 8 -> 24), with a
    forgotten id and a recycled one on the way, compiles nothing."""
    player = stream.Stream(sim_run, regions=conformal.Regions("dtaci", 0.1))
    assert player.warm_up(20) == (8, 16, 24)
    assert player.state.capacity == 8 and player.frames == 0
    xy = walkers(20, 30)
    with count_compiles() as compiles:
        for t in range(30):
            people = min(20, 2 + t)
            if t == 12:
                player.forget([0])
            if t == 20:
                xy[t:, 1] += 8.0                       # id 1 now names someone 8 m away
            out = player.step(np.arange(people), xy[t, :people])
    assert player.state.capacity == 24 and len(out.ids) == 20 and player.restarts == 1
    assert compiles.count == 0


def test_a_compilation_cache_gives_a_restarted_stream_its_programs(sim_run, tmp_path, caplog,
                                                                   own_compilation_cache):
    """Stream(compilation_cache=DIR) keeps the compiled step in DIR; a stream built after
    every in-memory program is gone (as in a restarted process) loads it from there."""
    folder = tmp_path / "xla"
    stream.Stream(sim_run, max_speed=3.0, compilation_cache=folder).warm_up(8)
    assert any("host_step" in path.name for path in folder.iterdir())
    stream_programs._jitted_step.cache_clear()
    jax.clear_caches()
    caplog.set_level(logging.DEBUG, logger="jax._src.compiler")
    stream.Stream(sim_run, max_speed=3.0, compilation_cache=folder).warm_up(8)
    loaded = [r.getMessage() for r in caplog.records
              if r.getMessage().startswith("Persistent compilation cache hit")]
    assert any("host_step" in message for message in loaded)


def test_a_restarted_robot_imports_only_what_predicting_needs():
    """Loading a shipped model and building a stream import neither orbax (0.15 s, read only
    for checkpoints) nor a jax dtype package that spends 0.6 s registering its types: the
    restarted process's first prediction stays under 2 s (benchmarks/bench_robot_loop.py)."""
    program = ("import sys, ml_dtypes; from gst_jax.runs import load_model; "
               "from gst_jax.conformal import Regions; from gst_jax.stream import Stream; "
               "Stream(load_model('pretrained:crowdnav_sj'), regions=Regions('dtaci', 0.1)); "
               "print('orbax.checkpoint' in sys.modules, ml_dtypes.__version__)")
    loaded, version = subprocess.run([sys.executable, "-c", program], capture_output=True,
                                     text=True, check=True).stdout.split()
    assert loaded == "False"
    assert tuple(int(part) for part in version.split(".")[:2]) < (0, 7)


def test_the_commands_that_compile_take_a_compilation_cache_folder(tmp_path, capsys,
                                                                    own_compilation_cache):
    from gst_jax import cli, evaluate, navigate
    from gst_jax.conformal import __main__ as conformal_command
    from gst_jax.predict import __main__ as predict_command

    for main, argv in [(conformal_command.main, ["--help"]), (predict_command.main, ["--help"]),
                       (evaluate.main, ["--help"]), (navigate.main, ["evaluate", "--help"])]:
        with pytest.raises(SystemExit):
            main(argv)
        assert "--compilation-cache DIR" in capsys.readouterr().out
    parser = cli.parser("test", "A command that compiles one program.")
    cli.add_compilation_cache_flag(parser)
    cli.run(lambda args: jax.jit(lambda x: x * 3.0 + 1.0)(jnp.arange(7.0)).block_until_ready(),
            parser, ["--compilation-cache", str(tmp_path / "cli")])
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "cli")
    assert any((tmp_path / "cli").iterdir())


def test_a_recycled_id_starts_a_new_track_and_the_old_persons_scores_are_dropped(sim_run):
    """A tracker recycles id 1 for someone 10 m away: a new track (nothing glued to the old
    history, no 10 m step predicted), and the old person's pending predictions are never
    scored against the newcomer; the other person's are."""
    player = stream.Stream(sim_run, regions=conformal.Regions("dtaci", 0.1))
    for t in range(8):
        out = player.step([1, 2], [[0.3 * t, 0.0], [5.0, 0.2 * t]])
    assert out.restarted.size == 0 and sorted(out.ids.tolist()) == [1, 2]
    out = player.step([1, 2], [[12.4, 0.0], [5.0, 1.6]])
    one, two = slot_of(player, 1), slot_of(player, 2)
    assert out.restarted.tolist() == [1] and player.restarts == 1
    np.testing.assert_array_equal(np.asarray(player.state.detected[one]), [0, 0, 0, 0, 1])
    assert out.ids.tolist() == [2]                   # the newcomer is seen once: not predicted
    assert not out.delayed.mask[one].any() and out.delayed.mask[two].all()
    for t in range(1, 6):                            # the newcomer walks on slowly
        out = player.step([1, 2], [[12.4 + 0.2 * t, 0.0], [5.0, 1.6 + 0.2 * t]])
        # Its own predictions' errors, never those of the old person's (about 10 m).
        assert out.delayed.scores[one].max() < 3.0
    assert sorted(out.ids.tolist()) == [1, 2] and player.restarts == 1


def test_a_jump_is_judged_over_the_steps_since_the_last_detection(sim_run):
    """The speed rule alone (max_acceleration=None), max_speed 2.5 m/s over steps of 0.25 s:
    unseen for two frames (3 steps), 1.5 m away is a walk (2 m/s), 2.6 m away another person
    (3.5 m/s); max_speed=None never restarts."""
    assert sim_run.model_config.step_s == 0.25
    for max_speed, expected in [(2.5, [[], [5]]), (None, [[], []])]:
        player = stream.Stream(sim_run, max_speed=max_speed, max_acceleration=None)
        for t in range(3):
            player.step([4, 5], [[0.0, 0.0], [0.25 * t, 0.0]])
        restarted = []
        for jump in (1.5, 2.6):
            x = float(np.asarray(player.state.positions[slot_of(player, 5), -1, 0]))
            player.step([4], [[0.0, 0.0]])
            player.step([4], [[0.0, 0.0]])
            restarted.append(player.step([4, 5], [[0.0, 0.0], [x + jump, 0.0]]).restarted
                             .tolist())
        assert restarted == expected


def test_a_forgotten_id_seen_again_is_a_new_track(sim_run):
    player = stream.Stream(sim_run, regions=conformal.Regions("dtaci", 0.1))
    for t in range(7):
        player.step([6, 7], [[0.3 * t, 0.0], [3.0, 0.3 * t]])
    player.forget([7, 99])                           # 99: never seen, nothing to forget
    out = player.step([6, 7], [[2.1, 0.0], [3.0, 2.1]])
    seven = slot_of(player, 7)
    np.testing.assert_array_equal(np.asarray(player.state.detected[seven]), [0, 0, 0, 0, 1])
    assert not out.delayed.mask[seven].any() and out.restarted.size == 0
    assert out.ids.tolist() == [6]
    assert sorted(player.step([6, 7], [[2.4, 0.0], [3.0, 2.4]]).ids.tolist()) == [6, 7]


def test_a_non_finite_detection_can_read_as_that_person_undetected(sim_run):
    with pytest.raises(DataError, match="not finite"):
        stream.Stream(sim_run).step([7, 8], [[np.nan, 0.0], [1.0, 1.0]])
    with pytest.raises(DataError, match="non_finite must be one of"):
        stream.Stream(sim_run, non_finite="drop")
    player = stream.Stream(sim_run, non_finite="undetected")
    for t in range(3):
        player.step([7, 8], [[0.3 * t, 0.0], [1.0, 0.2 * t]])
    out = player.step([7, 8], [[np.nan, 0.9], [1.0, 0.6]])
    assert out.ids.tolist() == [8]                   # 7 missed now: not predicted
    detected = np.asarray(player.state.detected)
    np.testing.assert_array_equal(detected[slot_of(player, 7)], [0, 1, 1, 1, 0])
    np.testing.assert_array_equal(detected[slot_of(player, 8)], [0, 1, 1, 1, 1])
    out = player.step([7, 8], [[np.inf, 0.0], [1.0, 0.8]])
    assert out.ids.tolist() == [8]


def test_positions_must_be_one_row_per_id_within_range(sim_run):
    player = stream.Stream(sim_run)
    with pytest.raises(DataError, match=r"a frame of 3 ids needs positions \(3, 2\): one "
                                        r"\(x, y\) row per id; got shape \(2, 3\)"):
        player.step([1, 2, 3], np.zeros((2, 3)))
    with pytest.raises(DataError, match=r"track 2's position \[1000000000.0, 0.0\] lies "
                                        r"beyond 1e\+04 m"):
        player.step([1, 2], [[0.0, 0.0], [1e9, 0.0]])
    assert player.frames == 0
    player.step([1, 2, 3], np.zeros((3, 2)))
    player.step([], [])
    assert player.frames == 2


@pytest.mark.parametrize("alpha", [float("nan"), 0.0, 1.0, -0.1, 1.5, "0.1"])
def test_regions_refuse_an_alpha_outside_0_1_in_one_line(alpha):
    with pytest.raises(DataError, match=r"^Regions: alpha \(the target miscoverage\) must lie "
                                        r"in \(0, 1\), got"):
        conformal.Regions("dtaci", alpha)


def test_the_docs_say_that_gensafenavs_released_file_gives_other_radii():
    """GenSafeNav's released DtACI truncates some losses to integers (np.vectorize infers an
    integer type): wherever the docs say our radii are GenSafeNav's, they say so."""
    docs = Path(__file__).parents[1] / "docs"
    claims = [line for name in ("robot.md", "benchmarks.md")
              for line in (docs / name).read_text().splitlines() if "same radii" in line]
    assert claims and all("truncat" in line for line in claims)


def test_each_capacitys_step_is_checked_before_it_first_runs(sim_run, monkeypatch):
    """Before a capacity's first step the stream hands it to `predict.compile_checked`, which
    refuses in one line what memory cannot hold and announces a crowd that is large for the
    exact model (issue 78); a later step of that capacity is not checked again."""
    seen = []
    check = stream_programs.compile_checked

    def recorded(program, args, config, slots, what, **options):
        seen.append(what)
        return check(program, args, config, slots, what, **options)

    monkeypatch.setattr(stream_programs, "compile_checked", recorded)
    player = stream.Stream(sim_run, max_speed=None, deadline_s=None)    # compiles in the loop
    xy = walkers(12, 3)
    for t, people in enumerate((4, 12, 12)):
        player.step(np.arange(people), xy[t, :people])
    assert seen == ["a stream step over 8 slots", "a stream step over 16 slots"]
    # Where the memory left cannot hold the compiler, the next new capacity is refused.
    monkeypatch.setattr(resources, "available_memory",
                        lambda device: (2 ** 20, "under a test's limit"))
    with pytest.raises(DataError, match=r"^a stream step over 24 slots: XLA's compiler needs"):
        player.step(np.arange(20), walkers(20, 1)[0])


def test_simultaneous_discs_hold_the_whole_horizon_at_the_target_within_acis_bound():
    """A recording of 4 tracks whose horizon-k errors are Rayleigh draws times k: one score per
    prediction (the max over its 3 steps of error / scale) through ACI covers all 3 steps
    together at 0.9 within Gibbs & Candes's bound with the delay (each score comes back 3
    frames, so up to 12 scores, late), every step inside exactly when the prediction is, and
    with smaller radii than Bonferroni's per-step discs. Measured: 0.8993, mean radius 1.567
    against 1.573 m (independent steps, where Bonferroni is nearly tight: 0.9026)."""
    rng = np.random.default_rng(0)
    frames, tracks, horizon = 3000, 4, 3
    scores = rng.rayleigh(0.3, (frames, tracks, horizon)) * np.arange(1, horizon + 1)
    recording = coverage.Recording([(scores, np.ones(scores.shape, bool),   # 300 warming up
                                     np.zeros((frames, tracks), bool))], frames, 300, 0.4, None)
    joint = coverage.simultaneous(recording, "aci", 0.1)
    gamma, delay = 0.005, horizon * tracks
    bound = (1 + gamma + delay * gamma) / (gamma * joint["joint_predictions"])
    assert joint["joint_predictions"] == (frames - horizon - 300) * tracks
    assert abs(joint["joint_coverage"] - 0.9) <= bound
    assert min(joint["coverage"]) >= joint["joint_coverage"]
    bonferroni, _ = coverage.measure(recording, "aci", 0.1, bonferroni=True)
    assert np.mean(joint["radius"]) < np.mean(bonferroni["radius"])


def test_simultaneous_discs_start_from_the_calibration_frames():
    """A hand-worked case: one track, horizon 2, 6 calibration frames. The predictions made at
    frames 0-3 are completed during them, with horizon-1 errors 0.3, 0.5, 0.7, 0.9 (sum 2.4)
    and horizon-2 errors 1.8, 0.6, 1.0, 1.4 (sum 4.8): with the prior of one error of 0.1 k m
    the scales are (2.4 + 0.1) / 5 = 0.5 and (4.8 + 0.2) / 5 = 1.0 m, and the scores
    max_k e_k / scale_k are 1.8, 1.0, 1.4, 1.8. At alpha 0.5, ACI's window holds the four
    (its radius the ceil(0.5 * 4) = 2nd smallest, 1.4), DtACI and PID start at their split
    conformal radius (the ceil(5 * 0.5) = 3rd smallest, 1.8). The one prediction made after
    the calibration (frame 6; those of frames 4 and 5 are not counted) gets radii q (0.5, 1.0)
    m and is observed 0.6 and 1.5 m off: inside at step 1 for every method, inside at step 2
    for DtACI and PID (1.5 <= 1.8) but not ACI (1.5 > 1.4)."""
    horizon, calibrating, frames = 2, 6, 9
    scores = np.full((frames, 1, horizon), 7.0)           # 7: errors of uncounted predictions
    for made, errors in enumerate([(0.3, 1.8), (0.5, 0.6), (0.7, 1.0), (0.9, 1.4), (5.0, 5.0),
                                   (5.0, 5.0), (0.6, 1.5)]):
        for k, error in enumerate(errors):          # horizon k + 1 comes back k + 1 frames later
            if made + k + 1 < frames:
                scores[made + k + 1, 0, k] = error
    recording = coverage.Recording([(scores, np.ones(scores.shape, bool),
                                     np.zeros((frames, 1), bool))], frames, calibrating, 0.4, None)
    for method, q in [("aci", 1.4), ("dtaci", 1.8), ("pid", 1.8)]:
        joint = coverage.simultaneous(recording, method, 0.5)
        assert joint["joint_predictions"] == 1, method                             # t0 = 6
        np.testing.assert_allclose(joint["radius"], [0.5 * q, 1.0 * q], rtol=1e-6)
        assert joint["coverage"] == [1.0, float(1.5 <= q)], method
        assert joint["joint_coverage"] == float(1.5 <= q), method


def test_a_streams_length_alone_spreads_its_coverage():
    """Exchangeable frames of i.i.d. errors: split conformal's whole-horizon coverage averages
    0.9 (it is exactly valid there) and spreads less around it the longer the stream."""
    rng = np.random.default_rng(4)

    def recording(frames):
        scores = rng.rayleigh(0.3, (frames, 3, 2)) * np.array([1.0, 2.0])
        return coverage.Recording([(scores, np.ones(scores.shape, bool),
                                    np.zeros((frames, 3), bool))], frames, frames * 3 // 10,
                                  0.4, None)

    short = coverage.exchangeable_coverage(recording(60), permutations=400)
    long = coverage.exchangeable_coverage(recording(1200), permutations=400)
    assert abs(long.mean() - 0.9) < 0.01 and abs(short.mean() - 0.9) < 0.03
    assert np.mean(np.abs(long - 0.9) <= 0.02) > 0.9 > 0.6 > np.mean(np.abs(short - 0.9) <= 0.02)


# --- Constant velocity with the same discs, and a GST stream saved and restored ----------------


def noisy_walkers(count: int, steps: int, step_s: float, noise_m: float, seed: int
                  ) -> np.ndarray:
    """(steps, count, 2) straight walks at up to 1.7 m/s, each position observed with
    Gaussian noise of noise_m metres per axis."""
    rng = np.random.default_rng(seed)
    start, velocity = rng.uniform(-6, 6, (count, 2)), rng.uniform(-1.2, 1.2, (count, 2))
    return (start + velocity * step_s * np.arange(steps)[:, None, None]
            + rng.normal(0, noise_m, (steps, count, 2)))


def test_a_constant_velocity_stream_repeats_each_tracks_last_step_and_covers_at_the_target():
    """Stream(ConstantVelocity(...), step_s=...) needs no model file: each track detected at
    the last two steps is predicted at its position plus k times its last displacement, and
    DtACI's discs around those predictions, checked here against the positions observed k
    steps later, hold them at about 1 - alpha at every horizon past their first 100 frames
    (here 0.896, every horizon within 0.889-0.902, over frames 100-299). Their ids
    are their own: no jump rule (max_speed=None), which noise of 0.1 m now and then trips."""
    step_s, horizon, frames, alpha = 0.4, 12, 300, 0.1
    xy = noisy_walkers(12, frames, step_s, 0.1, seed=1)
    player = stream.Stream(ConstantVelocity(obs_len=8, pred_len=horizon), step_s=step_s,
                           regions=conformal.Regions("dtaci", alpha), max_speed=None)
    steps = np.arange(1, horizon + 1)[None, :, None]
    inside, counted = np.zeros(horizon), np.zeros(horizon)
    for t in range(frames):
        out = player.step(np.arange(12), xy[t])
        np.testing.assert_array_equal(out.ids, np.arange(12 if t else 0))
        if t == 0:
            continue
        seen = xy[t - 1:t + 1].astype(np.float32)            # as the stream holds them
        expected = seen[1][:, None] + steps * (seen[1] - seen[0])[:, None]      # (12, P, 2)
        np.testing.assert_allclose(out.futures, expected, rtol=1e-6, atol=1e-5)
        assert out.radii.shape == (12, horizon) and np.isfinite(out.radii).all()
        if t >= 100:
            for k in range(min(horizon, frames - 1 - t)):
                error = np.linalg.norm(xy[t + k + 1] - out.futures[:, k], axis=-1)
                inside[k] += (error <= out.radii[:, k]).sum()
                counted[k] += 12
    assert counted.min() > 2000
    assert np.all(np.abs(inside / counted - (1 - alpha)) < 0.03), inside / counted
    assert abs(inside.sum() / counted.sum() - (1 - alpha)) < 0.015


def test_a_stream_without_a_model_is_refused_in_one_line_without_its_step(sim_run):
    cv = ConstantVelocity(obs_len=8, pred_len=12)
    for make, problem in [
            (lambda: stream.Stream(cv), "ConstantVelocity needs step_s"),
            (lambda: stream.Stream(cv, step_s=-0.4), "step_s must be at least 0.001"),
            (lambda: stream.Stream(cv, step_s=0.4, num_samples=20), "are a model's"),
            (lambda: stream.Stream(ConstantVelocity(obs_len=1), step_s=0.4),
             "needs obs_len of 2 or more"),
            (lambda: stream.Stream(sim_run, step_s=0.4), "a model steps at its own step_s")]:
        with pytest.raises(DataError, match=problem):
            make()


def test_a_gst_stream_restored_from_its_file_steps_as_one_that_never_stopped(sim_run, tmp_path):
    """The model's stream saved after 12 of 24 frames and restored into a new stream of the
    same model predicts and issues the same discs, bit for bit; a stream of other parameters
    (the same architecture) or of constant velocity refuses the file in one line."""
    xy = noisy_walkers(6, 24, sim_run.model_config.step_s, 0.05, seed=2)
    regions = conformal.Regions("dtaci", 0.1)
    player = stream.Stream(sim_run, regions=regions)
    outputs = [player.step(np.arange(6), xy[t]) for t in range(24)]
    replayed = stream.Stream(sim_run, regions=regions)
    for t in range(12):
        replayed.step(np.arange(6), xy[t])
    path = replayed.save(tmp_path / "robot.safetensors")
    restored = stream.Stream(sim_run, regions=regions, seed=9).load(path)
    for t in range(12, 24):
        out = restored.step(np.arange(6), xy[t])
        for name in ("ids", "futures", "radii"):
            np.testing.assert_array_equal(getattr(out, name), getattr(outputs[t], name))
    assert len(out.ids) == 6
    other = type("Run", (), {"model_config": sim_run.model_config,
                             "params": jax.tree.map(lambda p: p * 1.01, sim_run.params)})()
    with pytest.raises(DataError, match="saved by a stream of params_sha256 [0-9a-f]{64};"):
        stream.Stream(other, regions=regions).load(path)
    with pytest.raises(DataError, match="saved by a stream of predictor GST\\(config=Model"):
        stream.Stream(ConstantVelocity(obs_len=5, pred_len=5), step_s=0.25,
                      regions=regions).load(path)
