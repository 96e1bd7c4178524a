"""A crowd that comes and goes (issue 92): the stream's capacity shrinks back after a surge,
its tracks compacted, without flapping at a bucket's edge; a capacity not compiled yet
compiles in the background while constant velocity predicts on the host, the tracks kept
whole for the model to take over; a model step that fails, or overruns its deadline, falls
back the same way. The host's numpy step keeps the tracks as the core's `observe` does.

Every stream here is crowdnav_sim's with pooled DtACI discs (the programs of 8 and 16 slots,
those tests/test_stream.py compiles too). Where the values are compared, the streams wait for
the model (`deadline_s=None`, the suite's default: tests/conftest.py), so that no frame falls
back for the machine's load; where a deadline is the point, it is 1-30 s, reached only by the
tests' stand-ins for a compile or a step, which hold until the test lets them go."""

from __future__ import annotations

import logging
import threading

import jax
import numpy as np
import pytest

from gst_jax import conformal, resources, stream, stream_fallback, stream_programs
from gst_jax.adaptation import SpeedScale
from gst_jax.errors import DataError
from gst_jax.predict import checks as predict_checks
from gst_jax.predictors import ConstantVelocity
from gst_jax.runs import load_model

REGIONS = conformal.Regions("dtaci", 0.1)
P = 5                                       # crowdnav_sim's predicted steps, of 0.25 s


@pytest.fixture(scope="module")
def sim_run():
    return load_model("pretrained:crowdnav_sim")


@pytest.fixture
def release():
    """An event the test's stand-ins for compiling or stepping wait on, set at the end
    whatever happens: a thread left waiting would hold the process at its exit."""
    event = threading.Event()
    yield event
    event.set()


def walks(count: int, frames: int, seed: int = 3) -> np.ndarray:
    """(frames, count, 2) straight walks at up to 1.4 m/s from points of a 12 m square, 0.25 s
    a frame: constant velocity predicts them exactly."""
    rng = np.random.default_rng(seed)
    start, velocity = rng.uniform(-6, 6, (count, 2)), rng.uniform(-1, 1, (count, 2))
    return start + velocity * 0.25 * np.arange(frames)[:, None, None]


def constant_velocity(before: np.ndarray, now: np.ndarray) -> np.ndarray:
    """(N, P, 2): each of the positions `now` (N, 2) moving on by its step from `before`."""
    return now[:, None] + (now - before)[:, None] * np.arange(1, P + 1)[None, :, None]


def capacity_log(caplog) -> list[str]:
    return [r.getMessage().split(": ", 1)[1] for r in caplog.records
            if r.name == "gst_jax.stream" and "capacity" in r.getMessage()]


# --- The host's step keeps the tracks as the core's -------------------------------------------


@pytest.mark.parametrize("gate", [None, stream.Gate(0.6, 0.5, 0.1)])
def test_the_hosts_observe_keeps_the_tracks_as_the_cores(gate):
    """200 random frames of up to 12 of 30 ids over 16 slots, some ids lost, some jumping (the
    gate restarts them), more new ids than free slots at times (dropped): the numpy observe
    gives the jitted core's slots, histories and flags bit for bit."""
    observe = jax.jit(stream.observe, static_argnums=2)
    rng = np.random.default_rng(0)
    core = host = jax.tree.map(np.asarray, stream.init_state(16, 6))
    restarts = 0
    for t in range(200):
        ids = rng.choice(30, rng.integers(0, 13), replace=False).astype(np.int32)
        xy = (ids[:, None] * 0.3 + 0.1 * t + rng.normal(size=(len(ids), 2))).astype(np.float32)
        lost = rng.choice(30, rng.integers(0, 3), replace=False).astype(np.int32)
        frame = stream.Frame(np.pad(ids, (0, 16 - len(ids)), constant_values=stream.FREE),
                             np.pad(xy, [(0, 16 - len(ids)), (0, 0)]),
                             np.pad(lost, (0, 16 - len(lost)), constant_values=stream.FREE))
        core = jax.tree.map(np.asarray, observe(core, frame, gate))
        host = stream_fallback.observe(host, ids, xy, lost, gate)
        for name in ("track_ids", "positions", "detected", "dropped", "fresh", "restarted"):
            expected, got = getattr(core, name), getattr(host, name)
            assert got.dtype == expected.dtype, (t, name)
            np.testing.assert_array_equal(got, expected, err_msg=f"frame {t}: {name}")
        restarts += int(core.restarted.sum())
    assert int(core.dropped) > 0 and (gate is None or restarts > 0)


def test_the_tracks_a_frame_leaves_are_counted_before_it(sim_run):
    """`_held_after`, which sizes the state before the step, counts the tracks observe then
    holds (those still in their history, less the lost, plus the new ids), after idle empty
    steps too. Six walkers for 4 frames, 0 and 1 unseen at the 5th, 3 reported lost."""
    player = stream.Stream(sim_run, regions=REGIONS, deadline_s=None)
    xy = walks(12, 8)
    for t in range(4):
        player.step(np.arange(6), xy[t, :6])
    player.step(np.arange(2, 6), xy[4, 2:6])
    lost, empty = np.array([3], np.int32), (np.zeros(0, np.int32), np.zeros((0, 2)))
    counts = []
    for ids, idle in [(np.arange(4, 12), 0), (np.arange(4, 12), 3), (np.arange(4, 12), 4),
                      (np.array([3, 4]), 0)]:
        state = player._slots._resized(16)                   # room for them all
        for frame in [empty] * idle + [(ids, xy[5, ids])]:
            state = stream_fallback.observe(state, *frame, lost)
        counts.append(player._slots._held_after(ids, lost, idle))
        assert counts[-1] == int((state.track_ids != stream.FREE).sum())
    # 0, 1, 2, 4, 5 kept and 6-11 new; after 3 empty steps 0 and 1 are gone; after 4, all;
    # 3, lost and seen again, is a new track.
    assert counts == [11, 9, 8, 6]


# --- Shrinking after a crowd has gone ------------------------------------------------------------


def test_after_a_surge_the_capacity_shrinks_and_the_remaining_predictions_are_unchanged(
        sim_run, caplog):
    """Three walkers behind a crowd of 12 in the frames (so that the three hold slots 12-14
    of 16) for 10 frames, then the three alone: 4 frames (`shrink_after`) after the crowd's
    tracks have ended the stream is back at 8 slots, the three compacted into slots 0-2. Its
    predictions then equal those of a stream that never saw the crowd, and its discs and
    delayed scores (by track: the score buffer moved with them) those of a stream that never
    shrinks."""
    caplog.set_level(logging.INFO, logger="gst_jax.stream")
    shrinking = stream.Stream(sim_run, regions=REGIONS, deadline_s=None, shrink_after=4)
    staying = stream.Stream(sim_run, regions=REGIONS, deadline_s=None, shrink_after=None)
    alone = stream.Stream(sim_run, regions=REGIONS, deadline_s=None)
    xy = walks(15, 40)
    three = np.arange(100, 103)
    capacities, compared = [], 0
    for t in range(40):
        ids = np.concatenate([np.arange(12), three]) if t < 10 else three
        positions = xy[t] if t < 10 else xy[t, 12:]
        out, kept = shrinking.step(ids, positions), staying.step(ids, positions)
        reference = alone.step(three, xy[t, 12:])
        capacities.append(shrinking.state.capacity)
        assert out.fallback is None
        if t < 14:              # the crowd's tracks are held until 5 frames after its last
            continue
        np.testing.assert_array_equal(out.ids, reference.ids)
        np.testing.assert_allclose(out.futures, reference.futures, atol=2e-5, rtol=0)
        np.testing.assert_array_equal(out.ids, kept.ids)
        np.testing.assert_allclose(out.radii, kept.radii, rtol=1e-5)
        by_track = [dict(zip(np.asarray(s.state.track_ids).tolist(),
                             zip(o.delayed.scores, o.delayed.mask)))
                    for o, s in ((out, shrinking), (kept, staying))]
        for track in three.tolist():
            (scores, mask), (expected_scores, expected_mask) = (b[track] for b in by_track)
            np.testing.assert_array_equal(mask, expected_mask)
            np.testing.assert_allclose(scores, expected_scores, atol=2e-5, rtol=0)
            compared += int(mask.sum())
    # 3 held after frame 14's step, before and after from 15: the 4th such frame (18) shrinks.
    assert capacities == [16] * 18 + [8] * 22
    np.testing.assert_array_equal(np.asarray(shrinking.state.track_ids),
                                  [100, 101, 102] + [stream.FREE] * 5)
    assert staying.state.capacity == 16 and compared > 200
    assert capacity_log(caplog) == ["capacity 8 -> 16 slots (15 tracks)"] * 2 + [  # both grow
        "capacity 16 -> 8 slots (3 tracks; at most 3 for 4 frames)"]


def test_a_count_hovering_at_a_buckets_edge_does_not_flap(sim_run, caplog):
    """Warmed up for 8 and 16 slots; 12 walkers, then 8, with a ninth (a new one each time)
    every 8th frame: a track seen at t is held through t + 4 (obs_len 5), until t + 5's step
    ends it, so 8 tracks fit 8 slots before and after a step for 2 frames in a row at most and
    16 slots stay (shrink_after 4). Once the ninths stop, the 4th frame of 8 shrinks; the next
    ninth grows it again, from its compiled program (no constant velocity)."""
    caplog.set_level(logging.INFO, logger="gst_jax.stream")
    player = stream.Stream(sim_run, regions=REGIONS, deadline_s=30.0, shrink_after=4)
    assert player.warm_up(12) == (8, 16)
    xy = walks(12, 45)
    ninths = {7, 15, 23, 31, 41}
    capacities = []
    for t in range(45):
        ids = np.arange(12 if t == 0 else 8)
        positions = xy[t, :len(ids)]
        if t in ninths:
            ids, positions = np.append(ids, 100 + t), xy[t, :9]
        out = player.step(ids, positions)
        assert out.fallback is None
        capacities.append(player.state.capacity)
    # 12 held to frame 4 (and before 5's step), 9 at 7-11 (and before 12's), 15-19, 23-27,
    # 31-35: 8 before and after at 6, 13-14, 21-22, 29-30, then 37-40: the 4th of those (40)
    # shrinks; 41's ninth grows it.
    assert capacities == [16] * 40 + [8] + [16] * 4
    assert capacity_log(caplog) == ["capacity 8 -> 16 slots (12 tracks)",
                                    "capacity 16 -> 8 slots (8 tracks; at most 8 for 4 frames)",
                                    "capacity 8 -> 16 slots (9 tracks)"]


# --- Constant velocity where the model cannot predict in time -----------------------------------


def test_a_frame_needing_a_new_capacity_gets_constant_velocity_while_it_compiles(
        sim_run, monkeypatch, caplog, release):
    """Past the compiled capacity (8), a crowd of 12 gets constant velocity at once, not its
    program: the stream holds 16 slots and every track, and its predictions are the walks'
    own futures (constant velocity's, worked out here) until the compile, held back by the
    test, finishes; then the model predicts, as a stream that waited for it predicts. The
    crowd is announced once."""
    caplog.set_level(logging.INFO, logger="gst_jax.stream")
    xy = walks(12, 14)
    frames = [np.arange(3)] * 4 + [np.arange(12)] * 10
    waited = stream.Stream(sim_run, regions=REGIONS, deadline_s=None)
    expected = [waited.step(ids, xy[t, ids]) for t, ids in enumerate(frames)]

    compile_now = stream_programs._compile

    def held_back(*args):
        release.wait()
        return compile_now(*args)

    monkeypatch.setattr(stream_programs, "_compile", held_back)
    player = stream.Stream(sim_run, regions=REGIONS, deadline_s=30.0)
    release.set()                             # the first program compiles at the first step
    player.step(frames[0], xy[0, frames[0]])
    release.clear()
    outputs = []
    for t, ids in enumerate(frames[1:9], 1):
        outputs.append(player.step(ids, xy[t, ids]))
        assert player.state.capacity == (8 if t < 4 else 16)
    assert [o.fallback for o in outputs] == [None] * 3 + ["compiling"] * 5
    for t, out in enumerate(outputs[3:], 4):
        assert out.ids.tolist() == list(range(3 if t == 4 else 12))      # seen twice
        future = constant_velocity(xy[t - 1, out.ids], xy[t, out.ids])
        np.testing.assert_allclose(out.futures, future, atol=1e-5)
        assert not out.delayed.mask.any() and np.isfinite(out.radii).all()
    assert np.asarray(player.state.track_ids)[:12].tolist() == list(range(12))
    assert int(player.state.feed.step) == player.frames == 9     # the buffer's clock kept

    release.set()
    player._slots._finish_compiling()
    for t, ids in enumerate(frames[9:], 9):
        out = player.step(ids, xy[t, ids])
        assert out.fallback is None
        np.testing.assert_array_equal(out.ids, expected[t].ids)
        np.testing.assert_allclose(out.futures, expected[t].futures, atol=2e-5, rtol=0)
    announced = [r for r in caplog.records if "beyond the capacities compiled" in r.getMessage()]
    assert len(announced) == 1 and announced[0].levelno == logging.WARNING
    assert "12 tracks need 16 slots" in announced[0].getMessage()
    assert any("compiled a stream step over 16 slots in" in r.getMessage()
               for r in caplog.records)
    assert player.fallbacks == 5


def test_a_capacity_whose_compiling_memory_cannot_hold_is_refused_in_one_line(sim_run,
                                                                             monkeypatch):
    """The compile that would run in the background is refused at the frame that needs it,
    as a compile in the loop is (`check_compiler_room`): nothing started, nothing resized."""
    player = stream.Stream(sim_run, regions=REGIONS, deadline_s=30.0)
    xy = walks(12, 2)
    player.step(np.arange(3), xy[0, :3])                  # its first program: 8 slots
    monkeypatch.setattr(resources, "available_memory",
                        lambda device: (2 ** 20, "under a test's limit"))
    with pytest.raises(DataError, match=r"^a stream step over 16 slots: XLA's compiler needs"):
        player.step(np.arange(12), xy[1])
    assert player._slots._programs.compiling is None and player.state.capacity == 8


def test_every_predictors_step_is_weighed_against_the_memory_left(monkeypatch):
    """Only a gst_jax model's steps were weighed: CrowdNav++'s predictor over 2,048 people
    under a 2.2 GiB limit ran into XLA's RESOURCE_EXHAUSTED (issue 94). Constant velocity's
    step, with 1 kB left once compiled (the compiler's own room: the test above)."""
    monkeypatch.setattr(predict_checks, "check_compiler_room", lambda what, device=None: None)
    monkeypatch.setattr(resources, "available_memory",
                        lambda device: (1000, "under a test's limit"))
    player = stream.Stream(ConstantVelocity(obs_len=5, pred_len=P), step_s=0.25,
                           regions=REGIONS)
    with pytest.raises(DataError, match=r"^a stream step over 8 slots needs \d+ KiB \(XLA's "
                       r"estimate\); 1000 bytes is available \(under a test's limit\); use "
                       r"fewer people or more memory$"):
        player.step(np.arange(4), walks(4, 1)[0])


def test_warm_up_refuses_what_it_cannot_afford_before_compiling_the_rest(monkeypatch, caplog):
    """warm_up(10**6) compiled 57 programs in 7 minutes of 31,250 (issue 94): the largest
    compiles first, and the warm-up is refused in one line where the compiles would take
    longer than max_compile_s at its seconds each, or where its step needs more memory than
    is left; nothing else compiled, the stream as it was."""
    caplog.set_level(logging.INFO, logger="gst_jax.stream")
    player = stream.Stream(ConstantVelocity(obs_len=5, pred_len=P), step_s=0.25)
    with pytest.raises(DataError, match=r"^warm_up: 48 slots take 5 programs \(capacities 8 to "
                       r"48\), about \d+ s at the \d+\.\d s the largest took, beyond "
                       r"max_compile_s=1e-06; warm up to the crowd you expect, or give a "
                       r"larger max_compile_s \(None: no bound\)$"):
        player.warm_up(40, max_compile_s=1e-6)
    compiled = [r.getMessage().split(" in ")[0] for r in caplog.records
                if r.getMessage().startswith("compiled")]
    assert compiled == ["compiled a stream step over 48 slots"]
    assert player.state.capacity == 8
    monkeypatch.setattr(predict_checks, "check_compiler_room", lambda what, device=None: None)
    monkeypatch.setattr(resources, "available_memory",
                        lambda device: (1000, "under a test's limit"))
    with pytest.raises(DataError, match=r"^a stream step over 64 slots needs"):
        player.warm_up(60)
    assert len(caplog.records) == 1 and player.state.capacity == 8
    with pytest.raises(DataError, match=r"^warm_up: max_compile_s must be seconds above 0"):
        player.warm_up(8, max_compile_s=0)


def test_a_capacity_that_fails_to_compile_gets_constant_velocity_while_it_is_needed(
        sim_run, monkeypatch, caplog):
    """A background compile that raises: logged; constant velocity ("error") while the crowd
    needs that capacity (12 tracks, held to 4 frames after their last), the model again at
    the capacity compiled once they fit it, before the step and after."""
    caplog.set_level(logging.INFO, logger="gst_jax.stream")
    player = stream.Stream(sim_run, regions=REGIONS, deadline_s=30.0)
    xy = walks(12, 14)
    player.step(np.arange(3), xy[0, :3])                  # its first program: 8 slots

    def failing(*args):
        raise RuntimeError("LLVM ERROR: out of memory\nmore lines")

    monkeypatch.setattr(stream_programs, "_compile", failing)
    reasons = []
    for t in range(1, 14):
        ids = np.arange(12 if t < 4 else 3)
        reasons.append(player.step(ids, xy[t, ids]).fallback)
        if t == 1:
            player._slots._finish_compiling()
    # Frame 8's step ends the 9 tracks: the state before it still holds them.
    assert reasons == ["compiling"] + ["error"] * 7 + [None] * 5
    assert player.state.capacity == 8 and player._slots._programs.failed == {16}
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert errors == ["frame 2: compiling the step over 16 slots failed: RuntimeError: LLVM "
                      "ERROR: out of memory; constant velocity predicts while the crowd needs "
                      "them"]
    assert capacity_log(caplog)[-2:] == ["capacity 8 -> 16 slots (12 tracks)",
                                         "capacity 16 -> 8 slots (3 tracks; compiled)"]


def test_a_failing_step_falls_back_and_the_model_takes_over_after(sim_run, monkeypatch,
                                                                  caplog):
    """The model's step raising at one frame: that frame is constant velocity's
    (fallback "error", logged), the stream goes on, and the next frames are the model's,
    as a stream whose step never failed predicts them."""
    caplog.set_level(logging.INFO, logger="gst_jax.stream")
    xy = walks(5, 10)
    reference = stream.Stream(sim_run, regions=REGIONS, deadline_s=None)
    expected = [reference.step(np.arange(5), xy[t]) for t in range(10)]
    player = stream.Stream(sim_run, regions=REGIONS, deadline_s=None)
    call = stream_programs._call

    def failing_at_frame_5(step, args):
        if int(args[4]) == 5:
            raise RuntimeError("INTERNAL: a device fault\nmore lines")
        return call(step, args)

    monkeypatch.setattr(stream_programs, "_call", failing_at_frame_5)
    outputs = [player.step(np.arange(5), xy[t]) for t in range(10)]
    assert [o.fallback for o in outputs] == [None] * 5 + ["error"] + [None] * 4
    np.testing.assert_allclose(outputs[5].futures, constant_velocity(xy[4], xy[5]), atol=1e-5)
    for out, want in zip(outputs[6:], expected[6:]):
        np.testing.assert_allclose(out.futures, want.futures, atol=2e-5, rtol=0)
    warnings = [r.getMessage() for r in caplog.records
                if r.levelno == logging.WARNING and "constant velocity" in r.getMessage()]
    assert warnings == ["frame 5: constant velocity predicts: the model's step failed: "
                        "RuntimeError: INTERNAL: a device fault"]
    assert int(player.state.feed.step) == player.frames == 10


def test_a_step_past_its_deadline_falls_back_until_it_is_done(sim_run, monkeypatch, release):
    """A model step that does not return (held by the test) past the deadline: that frame and
    the next are constant velocity's ("overrun"), the stream never waiting for it; once it is
    done, the model predicts again (its late outputs unused), as a stream without the stall."""
    xy = walks(5, 10)
    reference = stream.Stream(sim_run, regions=REGIONS, deadline_s=None)
    expected = [reference.step(np.arange(5), xy[t]) for t in range(10)]
    # A deadline far beyond a step of 5 people (milliseconds), reached only by the held one.
    player = stream.Stream(sim_run, regions=REGIONS, deadline_s=1.0)
    call = stream_programs._call

    def held_at_frame_4(step, args):
        if int(args[4]) == 4:
            release.wait()
        return call(step, args)

    monkeypatch.setattr(stream_programs, "_call", held_at_frame_4)
    outputs = [player.step(np.arange(5), xy[t]) for t in range(6)]
    release.set()
    player._slots._programs.running.result()
    outputs += [player.step(np.arange(5), xy[t]) for t in range(6, 10)]
    assert [o.fallback for o in outputs] == [None] * 4 + ["overrun"] * 2 + [None] * 4
    assert player.overruns == 1
    for out, want in zip(outputs[6:], expected[6:]):
        np.testing.assert_allclose(out.futures, want.futures, atol=2e-5, rtol=0)


# --- Resizing moves each slot's state with its track ---------------------------------------------


def test_shrinking_moves_each_tracks_per_slot_state_with_it(sim_run):
    """Per-slot discs and an online correction: every per-slot array of a track (history,
    score buffer, conformal state, issued predictions) is where its track went, and the slots
    left are cut; nothing compiles (numpy)."""
    player = stream.Stream(sim_run, regions=conformal.Regions("aci", 0.1, pooled=False),
                           adaptation=SpeedScale(), capacity=16)
    state = jax.tree.map(np.array, player.state)
    mark = lambda a, axis: np.moveaxis(np.moveaxis(np.zeros_like(a), axis, 0)
                                       + np.arange(16).reshape((16,) + (1,) * (a.ndim - 1)),
                                       0, axis)
    track_ids = np.full(16, stream.FREE, np.int32)
    track_ids[[3, 9, 14]] = [7, 8, 9]
    state = state.replace(track_ids=track_ids, positions=mark(state.positions, 0),
                          feed=state.feed._replace(predicted=mark(state.feed.predicted, 1)),
                          regions=jax.tree.map(lambda a: mark(a, 0).astype(a.dtype),
                                               state.regions),
                          adaptation=state.adaptation._replace(issued=jax.tree.map(
                              lambda a: mark(a, 1).astype(a.dtype), state.adaptation.issued)))
    player.state = state
    small = player._slots._resized(8)
    assert small.capacity == 8
    np.testing.assert_array_equal(small.track_ids, [7, 8, 9] + [stream.FREE] * 5)
    slots = np.array([3, 9, 14, 0, 1, 2, 4, 5])          # the tracks', then the free, in order
    np.testing.assert_array_equal(small.positions[:, 0, 0], slots)
    np.testing.assert_array_equal(small.feed.predicted[0, :, 0, 0], slots)
    for leaf in jax.tree.leaves(small.regions):
        np.testing.assert_array_equal(leaf.reshape(8, -1)[:, 0], slots.astype(leaf.dtype))
    for leaf in jax.tree.leaves(small.adaptation.issued):
        np.testing.assert_array_equal(np.moveaxis(leaf, 1, 0).reshape(8, -1)[:, 0],
                                      slots.astype(leaf.dtype))
    player.state = small
    grown = player._slots._resized(16)
    np.testing.assert_array_equal(grown.track_ids[:3], [7, 8, 9])
    assert (grown.track_ids[3:] == stream.FREE).all() and grown.capacity == 16
    for leaf, before, fresh in zip(*map(jax.tree.leaves, (grown.regions, small.regions,
                                                          player._slots._fresh_regions))):
        np.testing.assert_array_equal(leaf[:8], before)
        np.testing.assert_array_equal(leaf[8:], np.repeat(fresh, 8, axis=0))


def test_deadline_and_shrink_after_are_refused_in_one_line(sim_run):
    with pytest.raises(DataError, match="deadline_s must be a positive number"):
        stream.Stream(sim_run, deadline_s=0)
    with pytest.raises(DataError, match="shrink_after must be a number of frames"):
        stream.Stream(sim_run, shrink_after=0)
