"""A tracker's frames as they come (issue 92): frame times resampled to the model's steps (a
5 Hz tracker predicts what a 4 Hz feed of the same people does; a jittered 10 Hz tracker that
drops frames is never refused), a gap advanced at once with the model run once, tracks that
keep their identity at a jogger's and a cyclist's speeds while a recycled id still restarts,
and lost ids given with their frame.

The references are computed without the code under test: straight walks written down at the
model's own steps, fed one frame per step (no times, no resampling), and hand-worked
interpolations.
"""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest

from gst_jax import conformal, stream
from gst_jax.adaptation import SpeedScale
from gst_jax.config import RULE, TimeGrid
from gst_jax.errors import DataError
from gst_jax.predictors import ConstantVelocity
from gst_jax.runs import load_model
from gst_jax.stream_time import Clock

STEP_S = 0.25             # crowdnav_sim's step


@pytest.fixture(scope="module")
def sim_run():
    run = load_model("pretrained:crowdnav_sim")
    assert run.model_config.step_s == STEP_S
    return run


def walks(count: int, seed: int = 3):
    """Straight walks at up to 1.4 m/s: the positions (N, 2) at any time (s)."""
    rng = np.random.default_rng(seed)
    start, velocity = rng.uniform(-4, 4, (count, 2)), rng.uniform(-1, 1, (count, 2))
    return lambda t: start + velocity * t


def per_step(run, positions_at, steps: int, origin: float = 0.0, enters=None) -> list:
    """The outputs of a stream fed one frame per model step (no times): the reference."""
    enters = {} if enters is None else enters
    player = stream.Stream(run)
    outputs = []
    for k in range(steps):
        t = origin + k * STEP_S
        seen = [i for i in range(len(positions_at(t))) if t >= enters.get(i, -np.inf)]
        outputs.append(player.step(seen, positions_at(t)[seen]))
    return outputs


def assert_same_predictions(output, reference, atol=0.05):
    assert sorted(output.ids.tolist()) == sorted(reference.ids.tolist())
    order, reference_order = np.argsort(output.ids), np.argsort(reference.ids)
    np.testing.assert_allclose(output.futures[order], reference.futures[reference_order],
                               rtol=0, atol=atol)


def test_a_5_hz_tracker_predicts_what_a_4_hz_feed_of_the_same_people_does(sim_run):
    """Straight walkers seen every 0.2 s (one entering at 1.1 s) against the same walkers
    seen every 0.25 s without times: the same people predicted, within 0.05 m, at every step;
    the frames that reach no step (0.2 s, 1.2 s, ...) repeat the last one's predictions."""
    positions_at = walks(3)
    enters = {2: 1.1}
    reference = per_step(sim_run, positions_at, 21, enters=enters)
    player = stream.Stream(sim_run)
    reached, last = [], None
    for k in range(26):
        t = 0.2 * k
        seen = [i for i in range(3) if t >= enters.get(i, -np.inf)]
        out = player.step(seen, positions_at(t)[seen], time=t)
        if out.repeated:
            assert last is not None and out.time == last.time
            np.testing.assert_array_equal(out.futures, last.futures)
            continue
        assert out.ticks == 1
        tick = round(out.time / STEP_S)
        assert out.time == pytest.approx(tick * STEP_S)
        assert_same_predictions(out, reference[tick])
        reached.append(tick)
        last = out
    assert reached == list(range(21))
    assert sorted(reference[6].ids.tolist()) == [0, 1, 2]      # the newcomer, from 1.5 s


def test_a_jittered_10_hz_tracker_that_drops_frames_is_never_refused(sim_run):
    """10 Hz, each frame +-20 ms off its time (and stamped with it), 3 % of the frames dropped:
    every frame is taken, every model step reached once, and the predictions are those of a
    feed at the model's steps from the first frame's time, within 0.05 m."""
    rng = np.random.default_rng(7)
    positions_at = walks(3, seed=5)
    times = 0.1 * np.arange(200) + rng.uniform(-0.02, 0.02, 200)
    kept = times[(rng.random(200) >= 0.03) | (np.arange(200) == 0)]
    assert len(kept) < 200
    reference = per_step(sim_run, positions_at, 80, origin=kept[0])
    player = stream.Stream(sim_run)
    ticks = 0
    for t in kept:
        out = player.step([0, 1, 2], positions_at(t), time=t)
        ticks += out.ticks
        if not out.repeated:
            tick = round((out.time - kept[0]) / STEP_S)
            assert_same_predictions(out, reference[tick])
            if tick >= 1:
                assert len(out.ids) == 3
    assert ticks == int((kept[-1] - kept[0]) / STEP_S) + 1


def test_a_frame_interpolates_between_the_detections_on_both_sides_of_a_step():
    """Hand-worked, on the clock alone: frames at 0, 0.1 and 0.3 s (0.2 s dropped) reach the
    steps at 0 and 0.25 s; at 0.25 s a track seen at 0.1 s (x = 1) and 0.3 s (x = 3) is at
    1 + 0.75 x 2 = 2.5; one first seen at 0.3 s is not detected there (nothing before it)."""
    clock = Clock(STEP_S)
    assert [t.number for t in clock.frame(10.0, np.array([1]), np.zeros((1, 2)), None).ticks] \
        == [0]
    assert clock.frame(10.1, np.array([1]), np.array([[1.0, 0.0]]), None).ticks == []
    [tick] = clock.frame(10.3, np.array([1, 2]), np.array([[3.0, 0.0], [5.0, 5.0]]), None).ticks
    assert (tick.number, tick.time) == (1, 10.25)
    assert tick.ids.tolist() == [1]
    np.testing.assert_allclose(tick.positions, [[2.5, 0.0]])
    with pytest.raises(DataError, match=r"^a frame at time 10\.2 s comes at or before the last "
                                        r"one \(10\.3 s\): frames must come in the order"):
        clock.frame(10.2, np.array([1]), np.zeros((1, 2)), None)
    assert Clock.from_json(clock.as_json()) == clock
    with pytest.raises(ValueError, match="must be a clock"):
        Clock.from_json({"ticks": 3})


def test_a_track_missed_in_one_frame_is_filled_in_once_seen_again(sim_run, caplog):
    """10 Hz: track 1 (x = 2t) is missing from the frame at 0.3 s, which reaches the step at
    0.25 s, so it is not predicted then; seen again at 0.4 s, that step is filled in at a
    quarter of the way from its detection at 0.2 s (x 0.4) to 0.4 s (x 0.8), x 0.5,
    and it is predicted at the next step (0.5 s). A frame 1.5 s later is logged as a
    gap."""
    player = stream.Stream(sim_run)
    outputs = {}
    for t in (0.0, 0.1, 0.2, 0.3, 0.4, 0.5):
        ids, xy = [0, 1], [[0.0, 1.0 + t], [2.0 * t, 0.0]]
        if t == 0.3:
            ids, xy = ids[:1], xy[:1]
        outputs[t] = player.step(ids, xy, time=t)
    assert outputs[0.3].time == 0.25 and outputs[0.3].ids.tolist() == [0]
    slot = int(np.flatnonzero(np.asarray(player.state.track_ids) == 1)[0])
    np.testing.assert_array_equal(np.asarray(player.state.detected[slot]), [0, 0, 1, 1, 1])
    np.testing.assert_allclose(np.asarray(player.state.positions[slot, 2:, 0]), [0, 0.5, 1.0],
                               atol=1e-6)
    assert outputs[0.5].time == 0.5 and sorted(outputs[0.5].ids.tolist()) == [0, 1]
    with caplog.at_level(logging.INFO, logger="gst_jax.stream"):
        player.step([0, 1], [[0.0, 3.0], [4.0, 0.0]], time=2.0)
    assert any("comes 1.500 s (6.0 model steps) after the last" in r.getMessage()
               for r in caplog.records)


@pytest.mark.parametrize("rate_hz", [None, 10.0])
def test_a_jogger_and_a_cyclist_keep_their_tracks_and_a_recycled_id_restarts(sim_run, rate_hz,
                                                                             caplog):
    """At the default gate, a steady 3 m/s jogger and a 6 m/s cyclist are predicted at every
    frame after their second detection (a step, or with times at 10 Hz, the second model
    step); a walker at 1 m/s whose id reappears 3 m from where it would be restarts once, its
    new track holding none of the old person's positions (nor a mix of the two)."""
    player = stream.Stream(sim_run)
    frame_s = STEP_S if rate_hz is None else 1 / rate_hz
    restarted = []
    with caplog.at_level(logging.INFO, logger="gst_jax.stream"):
        for k in range(int(4.0 / frame_s)):
            t = k * frame_s
            walker = [1.0 * t, 5.0] if t < 2.0 else [1.0 * t, 8.0]   # id 9 recycled at 2 s
            out = player.step([3, 6, 9], [[3.0 * t, 0.0], [0.0, -6.0 * t], walker],
                              time=None if rate_hz is None else t)
            if (rate_hz is None and k >= 1) or (rate_hz is not None and t >= STEP_S):
                assert {3, 6} <= set(out.ids.tolist()), (t, out.ids)
            restarted += out.restarted.tolist()
    assert restarted == [9] and player.restarts == 1
    assert any("tracks [9] restarted" in r.getMessage() for r in caplog.records)
    slot = int(np.flatnonzero(np.asarray(player.state.track_ids) == 9)[0])
    seen = np.asarray(player.state.detected[slot]) > 0
    np.testing.assert_allclose(np.asarray(player.state.positions[slot, :, 1])[seen], 8.0)


def test_a_gap_runs_the_model_once_and_scores_as_its_empty_steps_would(sim_run):
    """Frames with times and a gap of 7 steps, against frames without times and 6 empty frames
    in its place (what the stream ran before issue 92), with DtACI discs and SpeedScale: the
    same predictions, radii and scores after the gap, the compiled step called once for the
    frame after the gap. A gap beyond obs_len + pred_len steps, where max_gap_s allows it,
    runs it once too; a frame without a time then comes a step after the last."""
    positions_at = walks(3, seed=8)
    options = dict(regions=conformal.Regions("dtaci", 0.1), adaptation=SpeedScale())
    timed = stream.Stream(sim_run, max_gap_s=10.0, **options)
    reference = stream.Stream(sim_run, **options)
    steps = [k for k in range(30) if not 8 <= k <= 13]
    calls = []
    for k in range(30):
        if k in steps:
            out = timed.step([0, 1, 2], positions_at(k * STEP_S), time=k * STEP_S)
        expected = (reference.step([0, 1, 2], positions_at(k * STEP_S)) if k in steps
                    else reference.step([], np.zeros((0, 2))))
        if k == 1:                              # after its first call, which compile-checks
            programs = timed._slots._programs
            compiled = programs._step
            programs._step = lambda *args: calls.append(args[-1]) or compiled(*args)
        if k not in steps:
            continue
        assert_same_predictions(out, expected, atol=1e-5)
        np.testing.assert_allclose(out.radii, expected.radii, rtol=1e-6)
        np.testing.assert_array_equal(out.delayed.mask, expected.delayed.mask)
        np.testing.assert_allclose(out.delayed.scores, expected.delayed.scores, atol=1e-5)
    assert [int(idle) for idle in calls] == [0] * 6 + [6] + [0] * 15
    assert timed.frames == reference.frames == 30
    assert np.sum(expected.delayed.mask) > 0
    calls.clear()
    out = timed.step([0, 1, 2], positions_at(40.0), time=29 * STEP_S + 5.2)   # 20.8 steps
    assert [int(idle) for idle in calls] == [10] and out.ticks == 20
    assert timed.frames == 30 + 20 and out.ids.size == 0
    out = timed.step([0, 1, 2], positions_at(41.0))         # no time: step_s after the last
    assert (out.ticks, out.time, timed.frames) == (1, 50 * STEP_S, 51)


def test_lost_ids_given_with_their_frame_end_their_tracks_as_forget_does(sim_run):
    """step(..., lost=[7]) is forget([7]) before the frame: 7 seen again is a new track (seen
    once: not predicted), its old predictions never scored; not lost, it is one track."""
    players = [stream.Stream(sim_run, regions=conformal.Regions("dtaci", 0.1))
               for _ in range(3)]
    for t in range(7):
        for player in players:
            player.step([6, 7], [[0.3 * t, 0.0], [3.0, 0.3 * t]], time=t * STEP_S)
    frame = ([6, 7], [[2.1, 0.0], [3.0, 2.1]])
    players[0].forget([7, 99])                      # 99: never seen, nothing to forget
    outputs = [players[0].step(*frame, time=7 * STEP_S),
               players[1].step(*frame, time=7 * STEP_S, lost=[7, 99]),
               players[2].step(*frame, time=7 * STEP_S)]
    slots = [int(np.flatnonzero(np.asarray(p.state.track_ids) == 7)[0]) for p in players]
    for player, out, slot in zip(players[:2], outputs, slots):
        assert out.ids.tolist() == [6] and out.restarted.size == 0
        assert not out.delayed.mask[slot].any()
        np.testing.assert_array_equal(np.asarray(player.state.detected[slot]), [0, 0, 0, 0, 1])
    np.testing.assert_array_equal(outputs[0].delayed.mask, outputs[1].delayed.mask)
    assert sorted(outputs[2].ids.tolist()) == [6, 7] and outputs[2].delayed.mask[slots[2]].any()
    with pytest.raises(DataError, match="track ids must be integers"):
        players[0].step(*frame, time=8 * STEP_S, lost=[0.5])


def test_a_frame_too_long_after_the_last_is_refused_and_the_stream_goes_on():
    """Issue 94: time=1e9 after 0 went through 2.5e9 steps one by one (or raised an int32
    OverflowError at that step and every later one), and times in milliseconds were taken with
    nothing ever predicted. A frame more than max_gap_s after the last (by default obs_len +
    pred_len steps: 7 of 0.5 s here) is refused in one line and changes nothing: the next
    sane frame is predicted as if it had never come. Where the tracker did pause, the frame
    after the refused one confirms the jump and the tracks start afresh. Constant velocity,
    worked by hand: 1 m/s along x (id 1) and -y (id 2)."""
    player = stream.Stream(ConstantVelocity(obs_len=4, pred_len=3), step_s=0.5)
    ids = [1, 2]

    def at(t: float) -> np.ndarray:
        return np.array([[t, 0.0], [0.0, -t]])

    for t in (0.0, 0.5, 1.0):
        player.step(ids, at(t), time=t)
    with pytest.raises(DataError) as refused:
        player.step(ids, at(4.6), time=4.6)
    assert str(refused.value) == (
        "a frame at time 4.6 s comes 3.6 s (7.2 model steps) after the last one (1 s), more "
        "than max_gap_s 3.5 s (obs_len + pred_len model steps, beyond which nothing of the "
        "tracks is left): refused, the stream unchanged. Times must be seconds (in milliseconds "
        "a 10 Hz tracker's frames come 100 apart); after a real pause, the next frame within "
        "3.5 s after this one starts the tracks afresh (Stream(max_gap_s=...) allows longer "
        "gaps)")
    for t in (1e9, 101.0, 201.0):                # 1e9 s; then milliseconds, 100 apart
        with pytest.raises(DataError, match=re.escape(f"a frame at time {t:g} s comes "
                                                      f"{t - 1:g} s (")):
            player.step(ids, at(1.5), time=t)
    assert player.frames == 3
    out = player.step(ids, at(1.5), time=1.5)
    assert out.ids.tolist() == ids and player.frames == 4
    steps = 0.5 * np.arange(1, 4)[:, None]
    np.testing.assert_allclose(out.futures, [np.c_[1.5 + steps, 0 * steps],
                                             np.c_[0 * steps, -1.5 - steps]], atol=1e-6)

    with pytest.raises(DataError, match="after the last one"):      # a pause of a minute
        player.step(ids, at(61.5), time=61.5)
    out = player.step(ids, at(62.0), time=62.0)       # confirms it: the tracks start afresh
    assert out.ids.size == 0 and player.frames == 4 + 1 + 7
    out = player.step(ids, at(62.5), time=62.5)
    assert out.ids.tolist() == ids and player.frames == 13
    np.testing.assert_allclose(out.futures, [np.c_[62.5 + steps, 0 * steps],
                                             np.c_[0 * steps, -62.5 - steps]], atol=1e-4)

    # The step count is an int32 (the key folds it in): a frame past it is refused.
    player._slots.frames = 2**31 - 2
    player.step(ids, at(63.0), time=63.0)
    with pytest.raises(DataError, match=r"would take this stream past 2147483647 steps, the "
                                        r"most its step count \(int32\) holds"):
        player.step(ids, at(63.5), time=63.5)
    assert player.frames == 2**31 - 1


def test_times_that_cannot_be_seconds_and_bad_gap_bounds_are_refused():
    cv = ConstantVelocity(obs_len=4, pred_len=3)
    player = stream.Stream(cv, step_s=0.5)
    with pytest.raises(DataError, match=r"^a frame's time must be seconds \(from any origin, "
                                        r"within 1e\+10 of 0\), got 1\.7e\+12: a Unix time in "
                                        "milliseconds or nanoseconds"):
        player.step([1], [[0.0, 0.0]], time=1.7e12)
    assert player.frames == 0
    player.step([1], [[0.0, 0.0]], time=1.7e9)        # a Unix time in seconds
    for bad in (0.1, 2**16 * 0.5 + 1, "hour", True, float("nan")):
        with pytest.raises(DataError, match="^Stream: max_gap_s must be \"horizon\""):
            stream.Stream(cv, step_s=0.5, max_gap_s=bad)
    with pytest.raises(ValueError, match="from 0 to 2147483647"):
        Clock.from_json({**Clock(0.5).as_json(), "ticks": 2**31})


def test_a_time_step_outside_a_millisecond_to_a_minute_is_refused_in_one_line():
    """Issue 94: a step of 1e-300 s was taken (every frame then a jump of ~1e300 steps); now
    a step is from 1 ms to 60 s wherever it is set: a model's grid (its flags and config.json
    read the same rule), a stream without a model, a saved stream's clock."""
    cv = ConstantVelocity(obs_len=4, pred_len=3)
    for bad in (1e-300, 0.000999, 60.5):
        assert TimeGrid.__dataclass_fields__["step_s"].metadata[RULE].refusal(bad) is not None
        with pytest.raises(DataError, match=r"^Stream: step_s must be at (least 0\.001|most "
                                            rf"60), got {bad!r}$"):
            stream.Stream(cv, step_s=bad)
        with pytest.raises(ValueError, match=r"^must have a step from 0\.001 to 60 s$"):
            Clock.from_json({**Clock(0.5).as_json(), "step_s": bad})
    for good in (0.001, 60):
        assert stream.Stream(cv, step_s=good).grid.step_s == good
        assert Clock.from_json(Clock(good).as_json()).step_s == good
