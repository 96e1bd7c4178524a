"""ROS 2 bags without ROS (`gst_jax.io.ros2`, `python -m gst_jax.stream replay`): a bag of
tracked people written here replays into a bag whose paths are the stream's predictions and
whose discs carry the stream's radii, on the documented topics, in the input's frame, at the
input's stamps; a missing topic, another message type or a damaged file is refused in one
line."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import threading

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer

from gst_jax.conformal import Regions
from gst_jax.errors import DataError
from gst_jax.io import ros2
from gst_jax.predictors import ConstantVelocity
from gst_jax.runs import load_model
from gst_jax.stream import Stream, StreamOutput
from gst_jax.stream_commands import main

MODEL = "pretrained:crowdnav_sim"          # 0.25 s steps, as tests/test_stream.py's
STEP_NS = 250_000_000
START_NS = 1_700_000_000 * 10**9 + 125_000_000
TOPIC = "/tracks"
MISSING = 8                                 # the step no message was recorded at
ZERO_STAMP = 12                             # the message whose stamp is zero: its log time counts
STEPS = 16
# Each walker: its tracker's name, the steps it is seen at, its start and velocity (m/s), its
# turn (m/s^2 across its path); seen in order of names, not of the test's indices.
WALKERS = [("track-7", range(0, 11), (0.0, 0.0), (1.0, 0.2), 0.3),
           ("track-3", range(0, 16), (4.0, 1.0), (-0.8, 0.1), 0.0),
           ("person b", range(3, 16), (1.0, 3.0), (0.3, -0.9), -0.4),
           ("7", range(5, 16), (-2.0, 2.0), (0.9, 0.0), 0.2)]


def people_at(step: int) -> tuple[list[str], np.ndarray]:
    """The names and positions (M, 2) the tracker reports at a step."""
    names, positions = [], []
    for name, seen, start, velocity, turn in WALKERS:
        if step in seen:
            t = step * STEP_NS / 1e9
            heading = np.array(velocity) / np.linalg.norm(velocity)
            across = np.array([-heading[1], heading[0]])
            names.append(name)
            positions.append(np.array(start) + np.array(velocity) * t + 0.5 * turn * t**2 * across)
    return names, np.array(positions).reshape(-1, 2)


def people_message(names, positions, stamp_ns: int, frame_id: str = "map") -> dict:
    return {"header": {"stamp": {"sec": stamp_ns // 10**9, "nanosec": stamp_ns % 10**9},
                       "frame_id": frame_id},
            "people": [{"name": name, "position": {"x": x, "y": y, "z": 1.0},
                        "velocity": {"x": 9.0}, "reliability": 0.5}
                       for name, (x, y) in zip(names, positions.tolist())]}


def write_people(path, messages, topic: str = TOPIC) -> None:
    """(message, log time ns) pairs as a bag of people_msgs/msg/People."""
    with open(path, "wb") as file:
        writer = Writer(file)
        schema = writer.register_msgdef(ros2.PEOPLE, ros2.definition(ros2.PEOPLE))
        for message, log_time in messages:
            writer.write_message(topic, schema, message, log_time=log_time)
        writer.finish()


def recorded() -> list[tuple[int, int, dict]]:
    """(step, log time, message) of the walkers' bag: one message per step but MISSING, each
    logged a few ms after its stamp, but ZERO_STAMP's, which has no stamp."""
    messages = []
    for step in range(STEPS):
        if step == MISSING:
            continue
        stamp = START_NS + step * STEP_NS
        names, positions = people_at(step)
        log_time = stamp + 1_000_000 * (step % 5 + 1)
        if step == ZERO_STAMP:
            stamp = log_time = START_NS + step * STEP_NS
            messages.append((step, log_time, people_message(names, positions, 0)))
        else:
            messages.append((step, log_time, people_message(names, positions, stamp)))
    return messages


def read_bag(path) -> dict[str, list]:
    """topic -> [(schema name, log time, decoded message)] of a bag, in log time order."""
    topics: dict[str, list] = {}
    with open(path, "rb") as file:
        reader = make_reader(file, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            topics.setdefault(channel.topic, []).append((schema.name, message.log_time, decoded))
    return topics


def refusal(argv) -> str:
    """The one line `replay` ends with."""
    with pytest.raises(SystemExit) as ended:
        main(argv)
    message = str(ended.value)
    assert message.startswith("error: ") and "\n" not in message, message
    return message


@pytest.fixture(scope="module")
def run():
    return load_model(MODEL)


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("bags") / "walkers.mcap"
    write_people(path, [(message, log_time) for _, log_time, message in recorded()])
    return path


def the_streams_outputs(run) -> dict[int, StreamOutput]:
    """By step, what a Stream gives for the walkers' frames at their times (the missing step
    left out, as in the bag), the ids the test's own (100 + walker index)."""
    stream = Stream(run, regions=Regions("dtaci", 0.1))
    index = {name: k for k, (name, *_) in enumerate(WALKERS)}
    outputs = {}
    for step in range(STEPS):
        if step != MISSING:
            names, positions = people_at(step)
            outputs[step] = stream.step(np.array([100 + index[n] for n in names], np.int32),
                                        positions, time=(START_NS + step * STEP_NS) / 1e9)
    return outputs


def test_a_replayed_bag_holds_the_streams_predictions_and_discs(run, bag, tmp_path, capsys):
    out = tmp_path / "predictions.mcap"
    main(["replay", str(bag), "--out", str(out), "--model", MODEL, "--topic", TOPIC, "--json"])
    summary = json.loads(capsys.readouterr().out)
    expected = the_streams_outputs(run)
    messages = recorded()
    assert summary["frames"] == len(messages) == STEPS - 1
    assert summary["people"] == len(WALKERS) and summary["frame_id"] == "map"
    assert summary["topics"] == {ros2.PREDICTIONS_TOPIC: STEPS - 1, ros2.DISCS_TOPIC: STEPS - 1}
    written = read_bag(out)
    assert set(written) == {ros2.PREDICTIONS_TOPIC, ros2.DISCS_TOPIC}
    names = [name for name, *_ in WALKERS]
    predicted = discs = 0
    for k, (step, log_time, _) in enumerate(messages):
        stream_out = expected[step]
        futures = {names[i - 100]: f for i, f in zip(stream_out.ids.tolist(), stream_out.futures)}
        radii = {names[i - 100]: r for i, r in zip(stream_out.ids.tolist(), stream_out.radii)}
        stamp = START_NS + step * STEP_NS                 # the header's; ZERO_STAMP's log time
        for topic in (ros2.PREDICTIONS_TOPIC, ros2.DISCS_TOPIC):
            schema, logged, marker_array = written[topic][k]
            assert schema == ros2.MARKER_ARRAY and logged == log_time
            first, *markers = marker_array.markers
            assert first.action == ros2.DELETEALL
            for marker in marker_array.markers:
                assert marker.header.frame_id == "map"
                assert marker.header.stamp.sec * 10**9 + marker.header.stamp.nanosec == stamp
            if topic == ros2.PREDICTIONS_TOPIC:
                assert sorted(m.text for m in markers) == sorted(futures)
                for marker in markers:
                    assert marker.type == ros2.LINE_STRIP
                    points = np.array([[p.x, p.y] for p in marker.points])
                    np.testing.assert_allclose(points, futures[marker.text], rtol=0, atol=1e-5)
                    predicted += 1
            else:
                horizon = run.model_config.pred_len
                assert len(markers) == horizon * len(futures)
                for marker in markers:
                    assert marker.type == ros2.CYLINDER and marker.scale.x == marker.scale.y
                    row = marker.id % horizon                 # id: the track's x P + step
                    centre = [marker.pose.position.x, marker.pose.position.y]
                    np.testing.assert_allclose(centre, futures[marker.text][row], atol=1e-5)
                    np.testing.assert_allclose(marker.scale.x / 2, radii[marker.text][row],
                                               rtol=1e-6)
                    discs += 1
    assert predicted == summary["predictions"] > 30 and discs == summary["discs"]
    # the discs grew from their start (0.1 m per step) with the scores: DtACI ran
    assert len({round(float(r), 4) for out in expected.values() for r in out.radii.ravel()}) > 10


def test_a_frame_the_stream_refuses_is_named_by_its_message(tmp_path):
    """Stamps that go back in time: the stream's refusal, with where in the bag it came."""
    late = tmp_path / "late.mcap"
    names, positions = people_at(0)
    write_people(late, [(people_message(names, positions + 0.1 * k, START_NS - k * STEP_NS),
                         START_NS + k * STEP_NS) for k in range(3)])
    message = refusal(["replay", str(late), "--out", str(tmp_path / "o.mcap"), "--model", MODEL,
                       "--topic", TOPIC])
    assert f"{late}, message 2 on {TOPIC} (stamp {(START_NS - STEP_NS) / 1e9:.3f} s): " in message
    assert not (tmp_path / "o.mcap").exists() and not (tmp_path / "o.mcap.partial").exists()


def test_a_message_after_a_pause_beyond_the_horizon_is_skipped_and_the_replay_goes_on(
        run, tmp_path, caplog):
    """A tracker that paused 10 s, more than the stream's max_gap_s (crowdnav_sim's 5 + 5 steps,
    2.5 s): the message after the pause is skipped with one warning, the next confirms the jump
    and the tracks start afresh from it, predicted as by a stream that started there."""
    walkers = {"a": ((0.0, 0.0), (1.0, 0.2)), "b": ((4.0, 1.0), (-0.8, 0.1)),
               "c": ((1.0, 3.0), (0.3, -0.9))}                 # start (m), velocity (m/s)

    def people(names, step):
        return names, np.array([np.add(walkers[n][0], np.multiply(walkers[n][1], step / 4))
                                for n in names])
    steps = [*range(6), *range(45, 50)]                 # 6 to 44 not recorded: 10 s of pause
    seen = {step: people(["a", "b"] if step < 6 else ["a", "c"], step) for step in steps}
    bag = tmp_path / "pause.mcap"
    write_people(bag, [(people_message(*seen[step], START_NS + step * STEP_NS),
                        START_NS + step * STEP_NS) for step in steps])
    with caplog.at_level(logging.INFO, logger="gst_jax.stream"):
        summary = ros2.replay(run, bag, tmp_path / "out.mcap", topic=TOPIC, regions=None)
    assert (summary["frames"], summary["skipped"]) == (len(steps) - 1, 1)
    assert [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()] == [
        f"{bag}, message 7 on {TOPIC} (stamp {(START_NS + 45 * STEP_NS) / 1e9:.3f} s) skipped: "
        "it comes 10.000 s after the last frame, more than the stream's max_gap_s (2.5 s); the "
        "next message within 2.5 s of it starts the tracks afresh"]
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
    written = read_bag(tmp_path / "out.mcap")[ros2.PREDICTIONS_TOPIC]
    kept = [step for step in steps if step != 45]
    assert [logged for _, logged, _ in written] == [START_NS + step * STEP_NS for step in kept]
    afresh = Stream(run)
    for step, (*_, markers) in zip(kept, written):
        if step < 46:
            continue
        names, positions = seen[step]
        out = afresh.step(np.array([ord(n) for n in names]), positions,
                          time=(START_NS + step * STEP_NS) / 1e9)
        paths = {m.text: [[p.x, p.y] for p in m.points] for m in markers.markers[1:]}
        assert sorted(paths) == sorted(chr(i) for i in out.ids)
        for track, future in zip(out.ids.tolist(), out.futures):
            np.testing.assert_allclose(paths[chr(track)], future, rtol=0, atol=1e-5)
    assert len(paths) == 2                                  # a and c, not b


def test_a_bag_stamped_in_milliseconds_is_refused_instead_of_skipped_message_by_message(
        run, tmp_path, caplog):
    """Stamps in milliseconds read as seconds put 0.25 s frames 250 s apart: every message
    after the first was skipped, a warning each, and nothing predicted (issue 92). The replay
    ends at the tenth message in one line that names the likely cause, writing nothing."""
    names, positions = people_at(0)
    bag = tmp_path / "milliseconds.mcap"
    write_people(bag, [(people_message(names, positions + 0.1 * k, START_NS + k * 1000 * STEP_NS),
                        START_NS + k * STEP_NS) for k in range(12)])
    with pytest.raises(DataError, match=rf"^{bag}, message 10 on {TOPIC}: none of the 9 messages "
                       r"after the first came within the stream's max_gap_s \(2.5 s\) of the one "
                       r"before \(this one comes 2250.000 s after the last frame taken\): are the "
                       r"header stamps in seconds and nanoseconds\?"):
        ros2.replay(run, bag, tmp_path / "out.mcap", topic=TOPIC, regions=None)
    assert not list(tmp_path.glob("out.mcap*"))


def test_a_replay_keeps_out_of_the_log_only_its_own_streams_refusals(caplog):
    """The replay reports the frames its stream refuses itself, so it keeps the stream's own
    record of them out of the log; another stream of the process, in another thread, still
    logs its own."""
    def refused_frame(player):
        player.step([1], [[0.0, 0.0]], time=1.0)
        with pytest.raises(DataError, match="comes at or before the last one"):
            player.step([1], [[0.0, 0.0]], time=0.5)

    def constant_velocity():
        return Stream(ConstantVelocity(obs_len=5, pred_len=5), step_s=0.25)
    with caplog.at_level(logging.ERROR, logger="gst_jax.stream"), ros2._refusals_reported_here():
        refused_frame(constant_velocity())                        # the replay's own thread
        other = threading.Thread(target=refused_frame, args=(constant_velocity(),))
        other.start()
        other.join()
    assert [r.thread for r in caplog.records] == [other.ident]


def test_bags_that_cannot_be_replayed_are_refused_in_one_line(bag, tmp_path):
    out = ["--out", str(tmp_path / "out.mcap"), "--model", MODEL]
    assert "has no topic /people (its topics: /tracks (people_msgs/msg/People))" in refusal(
        ["replay", str(bag), *out])
    chatter = tmp_path / "chatter.mcap"
    with open(chatter, "wb") as file:
        writer = Writer(file)
        schema = writer.register_msgdef("std_msgs/msg/String", "string data")
        writer.write_message("/people", schema, {"data": "hello"}, log_time=1)
        writer.finish()
    assert "topic /people holds std_msgs/msg/String, not people_msgs/msg/People" in refusal(
        ["replay", str(chatter), *out])
    data = bag.read_bytes()
    for name, damaged in [("truncated", data[: len(data) // 2]), ("text", b"no bag here\n" * 9),
                          ("empty", b"")]:
        path = tmp_path / f"{name}.mcap"
        path.write_bytes(damaged)
        assert "not a readable MCAP bag" in refusal(["replay", str(path), *out, "--topic", TOPIC])
    assert "no such file" in refusal(["replay", str(tmp_path / "gone.mcap"), *out])
    assert "is the input bag" in refusal(["replay", str(bag), "--out", str(bag)])
    names, positions = people_at(5)
    twice = tmp_path / "twice.mcap"
    write_people(twice, [(people_message(names + names[:1], np.vstack([positions, positions[:1]]),
                                         START_NS), START_NS)])
    assert "'track-7' appears twice in one message" in refusal(
        ["replay", str(twice), *out, "--topic", TOPIC])
    moved = tmp_path / "moved.mcap"
    write_people(moved, [(people_message(names, positions, START_NS + k * STEP_NS,
                                         "map" if k == 0 else "odom"), START_NS + k * STEP_NS)
                         for k in range(2)])
    assert "one fixed world frame" in refusal(["replay", str(moved), *out, "--topic", TOPIC])
    assert not list(tmp_path.glob("out.mcap*"))


def test_markers_without_regions_and_with_an_unbounded_radius():
    header = {"stamp": {"sec": 3, "nanosec": 5}, "frame_id": "map"}
    futures = np.arange(12, dtype=np.float32).reshape(2, 3, 2)
    paths, discs = ros2.prediction_markers(StreamOutput(np.array([4, 9]), futures), ["a", "b"],
                                           header)
    assert discs is None
    assert [(m["id"], m["text"]) for m in paths["markers"][1:]] == [(4, "a"), (9, "b")]
    assert paths["markers"][2]["points"][1] == {"x": 8.0, "y": 9.0}
    radii = np.array([[0.5, np.inf, 1.0], [0.25, 0.5, 0.75]], np.float32)
    _, discs = ros2.prediction_markers(StreamOutput(np.array([4, 9]), futures, radii), ["a", "b"],
                                       header)
    assert [(m["id"], m["scale"]["x"]) for m in discs["markers"][1:]] == [
        (12, 1.0), (14, 2.0), (27, 0.5), (28, 1.0), (29, 1.5)]


def test_python_m_gst_jax_stream_runs_the_replay_command(bag, tmp_path):
    done = subprocess.run([sys.executable, "-m", "gst_jax.stream", "replay", str(bag), "--out",
                           str(tmp_path / "out.mcap"), "--model", MODEL, "--topic", "/nope"],
                          capture_output=True, text=True)
    assert done.returncode == 1
    assert done.stderr.strip().splitlines() == [
        f"error: {bag} has no topic /nope (its topics: {TOPIC} (people_msgs/msg/People)): "
        f"name the one of {ros2.PEOPLE} with --topic"]
