"""ROS 2 without ROS: tracked people from a bag (MCAP) into a `Stream`, its predictions and
discs out as messages that Foxglove and RViz show (`python -m gst_jax.stream replay`).

    frame = people_frame(message, log_time_ns)        # a decoded people_msgs/msg/People
    names = TrackNames()
    out = stream.step(names.ids_of(frame.names), frame.positions, time=frame.time_s)
    paths, discs = prediction_markers(out, names.names_of(out.ids), frame.header)

The input is `people_msgs/msg/People` (wg-perception/people, which has a ROS 2 branch): the
message Nav2's social costmap layers subscribe to on `/people` and ROS 2 leg and people
trackers publish, one message per tracker update with a header (stamp, frame_id) and per person
a `name` (the track's id, a string) and a `position` (metres). `geometry_msgs/msg/PoseArray`
carries no ids at all (GenSafeNav's ROS 2 tracker sends them beside it as JSON text), and
`spencer_tracking_msgs` is ROS 1's. A person's velocity, reliability and tags are not read: the
stream keeps each track's history itself.

The output, one message per input message on each topic (but the messages `replay` skips),
stamped with the input's header stamp
(its log time where that is zero), in the input's frame_id, logged at the input's log time:
`PREDICTIONS_TOPIC` (a LINE_STRIP per predicted person, its points the predicted positions 1..P
steps ahead, `id` the stream's id and `text` the tracker's name) and `DISCS_TOPIC` (a CYLINDER
per predicted step k = 0..P-1, `id` the stream's id x P + k, centred on the predicted position,
`scale.x` = `scale.y` = twice the conformal radius; a step whose radius is infinite, unbounded
so far, has none). Each message starts with a DELETEALL marker, so people no longer predicted
vanish. A message more than the stream's `max_gap_s` after the last (the model's obs_len +
pred_len steps: a tracker's pause, or a stray stamp) is skipped with a warning (logger
"gst_jax.stream"); the next message within max_gap_s of it starts the tracks afresh.

Nothing here imports rclpy: a ROS 2 node (examples/ros2_node/) uses the same functions on the
messages it receives, and turns the markers' dicts into messages with
`rosidl_runtime_py.set_message_fields`. Bags are read and written with the `mcap` and
`mcap-ros2-support` packages (`pip install "gst_jax[ros]"`), imported only by the functions that
touch a bag, which decode with the schema text stored in the bag and encode with the
definitions below.

One job, though over 400 lines: a bag of people in, a bag of predictions out; the message
definitions, the decoding of the one and the encoding of the other stay beside the replay that
joins them, so that what a replay writes is read against what it reads.
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import os
import re
import threading
import time
from pathlib import Path
from typing import Any, Iterator, NamedTuple

import numpy as np

from gst_jax.conformal import Regions
from gst_jax.errors import DataError
from gst_jax.progress import Progress
from gst_jax.stream import Stream, StreamOutput
from gst_jax.stream_time import FrameGap

logger = logging.getLogger("gst_jax.stream")

PEOPLE = "people_msgs/msg/People"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
PEOPLE_TOPIC = "/people"
PREDICTIONS_TOPIC = "/gst/predictions"
DISCS_TOPIC = "/gst/discs"

# Marker's type and action codes (visualization_msgs/msg/Marker's constants).
LINE_STRIP, CYLINDER, DELETEALL = 4, 3, 3
# Metres: the width of a predicted path's line and the height of a disc.
LINE_WIDTH, DISC_HEIGHT = 0.05, 0.02
PATH_COLOUR = {"r": 1.0, "g": 0.5, "b": 0.0, "a": 1.0}
DISC_COLOUR = {"r": 0.2, "g": 0.5, "b": 1.0, "a": 0.25}
# `replay`'s discs unless told otherwise: the stream's default method at a miscoverage of 0.1.
DEFAULT_REGIONS = Regions("dtaci", 0.1)
# A bag whose first messages all come more than max_gap_s after the one before is refused
# after this many (stamps in the wrong unit: milliseconds as seconds put a 10 Hz tracker's
# messages 100 s apart), rather than skipping every message with a warning each.
SKIPPED_FROM_THE_START = 10

# The fields of each message read or written, every type named in full (so that a message's
# dependencies are the types its fields name). From ros2/common_interfaces (branch jazzy;
# humble's fields are the same), ros2/rcl_interfaces (builtin_interfaces) and
# wg-perception/people (branch ros2); their constants and comments left out (no part of the
# encoding).
FIELDS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "builtin_interfaces/Duration": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "std_msgs/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation",
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data",
    "visualization_msgs/UVCoordinate": "float32 u\nfloat32 v",
    "visualization_msgs/MeshFile": "string filename\nuint8[] data",
    "visualization_msgs/Marker": "\n".join([
        "std_msgs/Header header", "string ns", "int32 id", "int32 type", "int32 action",
        "geometry_msgs/Pose pose", "geometry_msgs/Vector3 scale", "std_msgs/ColorRGBA color",
        "builtin_interfaces/Duration lifetime", "bool frame_locked",
        "geometry_msgs/Point[] points", "std_msgs/ColorRGBA[] colors", "string texture_resource",
        "sensor_msgs/CompressedImage texture", "visualization_msgs/UVCoordinate[] uv_coordinates",
        "string text", "string mesh_resource", "visualization_msgs/MeshFile mesh_file",
        "bool mesh_use_embedded_materials"]),
    "visualization_msgs/MarkerArray": "visualization_msgs/Marker[] markers",
    "people_msgs/Person": "string name\ngeometry_msgs/Point position\ngeometry_msgs/Point "
                          "velocity\nfloat64 reliability\nstring[] tagnames\nstring[] tags",
    "people_msgs/People": "std_msgs/Header header\npeople_msgs/Person[] people",
}


def definition(datatype: str) -> str:
    """The schema text of a message type ("pkg/msg/Type") as rosbag2 stores it in a bag: its
    fields, then each type they depend on after a line of '=' and `MSG: pkg/Type`."""
    package, _, name = datatype.split("/")
    order: list[str] = []

    def visit(type_name: str) -> None:
        for line in FIELDS[type_name].splitlines():
            used = line.split()[0].removesuffix("[]")
            if "/" in used and used not in order:
                order.append(used)
                visit(used)
    visit(f"{package}/{name}")
    return "\n".join([FIELDS[f"{package}/{name}"]] + [
        f"{'=' * 80}\nMSG: {used}\n{FIELDS[used]}" for used in order])


class PeopleFrame(NamedTuple):
    """One People message as a stream's frame: time_s, the header stamp in seconds (the log
    time where the stamp is zero); header, the stamp used and the frame_id as a Header dict;
    names (M,), the tracker's ids; positions (M, 2), metres in the frame_id's frame."""

    time_s: float
    header: dict
    names: list[str]
    positions: np.ndarray


def people_frame(message: Any, log_time_ns: int | None = None) -> PeopleFrame:
    """A people_msgs/msg/People message (decoded from a bag, or an rclpy message) as a frame.
    A name given twice in one message is refused (`DataError`)."""
    stamp = message.header.stamp
    sec, nanosec = int(stamp.sec), int(stamp.nanosec)
    if sec == 0 and nanosec == 0 and log_time_ns is not None:
        sec, nanosec = divmod(int(log_time_ns), 1_000_000_000)
    names = [str(person.name) for person in message.people]
    if len(set(names)) != len(names):
        twice = next(name for name in names if names.count(name) > 1)
        raise DataError(f"person {twice!r} appears twice in one message: each person of a "
                        "People message needs a name (track id) of its own")
    positions = np.array([[person.position.x, person.position.y] for person in message.people],
                         np.float64).reshape(len(names), 2)
    header = {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": str(message.header.frame_id)}
    return PeopleFrame(sec + nanosec * 1e-9, header, names, positions)


class TrackNames:
    """The stream's integer ids for a tracker's names: each name new to it takes the next
    integer (0, 1, ...), and keeps it."""

    def __init__(self):
        self.ids: dict[str, int] = {}
        self.names: list[str] = []

    def ids_of(self, names: list[str]) -> np.ndarray:
        """(M,) int32 ids of these names."""
        for name in names:
            if name not in self.ids:
                self.ids[name] = len(self.names)
                self.names.append(name)
        return np.array([self.ids[name] for name in names], np.int32)

    def names_of(self, ids) -> list[str]:
        return [self.names[int(i)] for i in ids]


def prediction_markers(output: StreamOutput, names: list[str], header: dict
                       ) -> tuple[dict, dict | None]:
    """One frame's MarkerArrays, as dicts (what the bag writer and
    `rosidl_runtime_py.set_message_fields` take): the predicted paths, and the discs (None
    without regions). output: a mean-mode `StreamOutput` (futures (L, P, 2), radii (L, P));
    names (L,): the tracker's names of `output.ids`; header: the input's (`PeopleFrame`)."""
    clear = {"header": header, "action": DELETEALL}
    paths, discs = [clear], [clear]
    horizon = output.futures.shape[1]
    for row, (track, name) in enumerate(zip(output.ids.tolist(), names)):
        future = output.futures[row]                                              # (P, 2)
        paths.append({"header": header, "ns": "predictions", "id": track, "type": LINE_STRIP,
                      "pose": {"orientation": {"w": 1.0}}, "scale": {"x": LINE_WIDTH},
                      "color": PATH_COLOUR, "text": name,
                      "points": [{"x": float(x), "y": float(y)} for x, y in future]})
        if output.radii is None:
            continue
        for step, ((x, y), radius) in enumerate(zip(future, output.radii[row].tolist())):
            if math.isfinite(radius):
                discs.append({"header": header, "ns": "discs", "id": track * horizon + step,
                              "type": CYLINDER, "text": name,
                              "pose": {"position": {"x": float(x), "y": float(y)},
                                       "orientation": {"w": 1.0}},
                              "scale": {"x": 2 * radius, "y": 2 * radius, "z": DISC_HEIGHT},
                              "color": DISC_COLOUR})
    return {"markers": paths}, None if output.radii is None else {"markers": discs}


def read_people(path: Path, topic: str) -> Iterator[tuple[int, PeopleFrame]]:
    """(log time in ns, frame) of each People message on `topic` of the bag at `path`, in log
    time order. A file that is not a readable MCAP bag, a topic it lacks or one of another
    type is refused in one line (`DataError`)."""
    _require_bag_packages()
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as file:
        with _unreadable_as_data_error(path):
            reader = make_reader(file)
            summary = reader.get_summary()
        topics = None if summary is None else {
            channel.topic: _schema_name(summary.schemas.get(channel.schema_id))
            for channel in summary.channels.values()}
        if topics is not None:
            _check_topic(path, topic, topics)
        messages, decoders, count = reader.iter_messages(topics=[topic]), DecoderFactory(), 0
        while True:
            with _unreadable_as_data_error(path):
                item = next(messages, None)
                if item is None:
                    break
                schema, channel, message = item
                _check_topic(path, topic, {topic: _schema_name(schema)})
                with contextlib.redirect_stderr(io.StringIO()):   # its parser prints as it fails
                    decode = decoders.decoder_for(channel.message_encoding, schema)
                if decode is None:
                    raise DataError(f"{path}: topic {topic}'s messages are encoded as "
                                    f"{channel.message_encoding!r}, not as ROS 2's CDR")
                frame = people_frame(decode(message.data), message.log_time)
            count += 1
            yield message.log_time, frame
        if count == 0:
            if topics is None:             # no summary: the topics its messages are on
                with _unreadable_as_data_error(path):
                    file.seek(0)
                    topics = {channel.topic: _schema_name(schema) for schema, channel, _
                              in make_reader(file).iter_messages()}
                _check_topic(path, topic, topics)
            raise DataError(f"{path}: topic {topic} holds no messages")


def _require_bag_packages() -> None:
    """Refuse in one line where the packages that read and write bags are not installed."""
    import importlib.util

    if any(importlib.util.find_spec(name) is None for name in ("mcap", "mcap_ros2")):
        raise DataError("reading and writing ROS 2 bags needs the packages mcap and "
                        "mcap-ros2-support: pip install \"gst_jax[ros]\"")


def _schema_name(schema) -> str:
    return "(no schema)" if schema is None else schema.name


def _check_topic(path: Path, topic: str, topics: dict[str, str]) -> None:
    """Refuse a topic the bag lacks, or one that holds another type than People (whose name
    rosbag2 writes as pkg/msg/Type, some writers as pkg/Type)."""
    if topic not in topics:
        held = ", ".join(f"{name} ({kind})" for name, kind in sorted(topics.items())) or "none"
        raise DataError(f"{path} has no topic {topic} (its topics: {held}): name the one of "
                        f"{PEOPLE} with --topic")
    if topics[topic] not in (PEOPLE, PEOPLE.replace("/msg/", "/")):
        raise DataError(f"{path}: topic {topic} holds {topics[topic]}, not {PEOPLE} (tracked "
                        "people with names and positions: docs/robot.md, 'Replaying a ROS 2 "
                        "bag')")


@contextlib.contextmanager
def _unreadable_as_data_error(path: Path):
    """Whatever the MCAP reader or the CDR decoder raise on a damaged file (their own errors,
    but also KeyError, struct.error, UnicodeDecodeError, zstd's...) as one line."""
    try:
        yield
    except (DataError, MemoryError):
        raise
    except Exception as error:
        raise DataError(f"{path}: not a readable MCAP bag ({type(error).__name__}: "
                        f"{_one_line(error)}): a truncated or damaged file?") from None


def _one_line(error: Exception) -> str:
    text = re.sub(r"\s+", " ", str(error)).strip()
    return text[:200] + ("..." if len(text) > 200 else "")


class BagWriter:
    """MarkerArrays into an MCAP bag (ROS 2's CDR, the definitions above), one channel per
    topic: `write(topic, markers, log_time_ns)`, `finish()`."""

    def __init__(self, file):
        from mcap_ros2.writer import Writer

        self._writer = Writer(file)
        self._schema = self._writer.register_msgdef(MARKER_ARRAY, definition(MARKER_ARRAY))
        self.counts: dict[str, int] = {}

    def write(self, topic: str, markers: dict, log_time_ns: int) -> None:
        self._writer.write_message(topic, self._schema, markers, log_time=log_time_ns,
                                   sequence=self.counts.get(topic, 0))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def finish(self) -> None:
        self._writer.finish()


def replay(run, source: str | Path, out: str | Path, *, topic: str = PEOPLE_TOPIC,
           regions: Regions | None = DEFAULT_REGIONS, progress: Progress | None = None
           ) -> dict:
    """Play the People messages of the bag `source` on `topic` through a `Stream` of `run`
    (mean mode, each frame at its header stamp) and write its predictions and discs to the bag
    `out` (the module's docstring says how). The people must be in one fixed frame (a world
    frame, metres), stamped in seconds (resampled to the model's steps as `Stream.step(time=)`
    does). A message more than the stream's max_gap_s after the last one is skipped with a
    warning (logger "gst_jax.stream"), and the next within max_gap_s of it starts the tracks
    afresh (`Stream(max_gap_s=)`); any other frame the stream refuses ends the replay. Returns a
    summary: frames, people, predictions and discs written, frames skipped, the topics'
    message counts."""
    source, out = Path(source), Path(out)
    _require_bag_packages()
    if not source.is_file():
        raise DataError(f"{source}: no such file (a ROS 2 bag in MCAP format, e.g. from "
                        f"`ros2 bag record -s mcap {topic}`)")
    if out.exists() and out.resolve() == source.resolve():
        raise DataError(f"--out {out} is the input bag: write the predictions to another file")
    total = _checked_bag(source, topic)
    # A replay is offline: every frame waits for the model (no constant-velocity fallback on
    # a step slower than the model's period), so that the bag holds the model's predictions.
    stream, names = Stream(run, regions=regions, deadline_s=None), TrackNames()
    frames = predictions = discs_written = skipped = 0
    frame_id: str | None = None
    partial = out.with_name(out.name + ".partial")      # a bag whole or none: replaced at the end
    started = time.perf_counter()
    try:
        with open(partial, "wb") as file, _refusals_reported_here():
            writer = BagWriter(file)
            for log_time, frame in read_people(source, topic):
                where = f"{source}, message {frames + skipped + 1} on {topic}"
                frame_id = _same_frame(frame_id, frame.header["frame_id"], where)
                try:
                    output = stream.step(names.ids_of(frame.names), frame.positions,
                                         time=frame.time_s)
                except FrameGap as gap:
                    skipped += 1
                    if frames == 1 and skipped + 1 >= SKIPPED_FROM_THE_START:
                        raise DataError(
                            f"{where}: none of the {skipped} messages after the first came "
                            f"within the stream's max_gap_s ({gap.max_gap_s:g} s) of the one "
                            f"before (this one comes {gap.gap_s:.3f} s after the last frame "
                            "taken): are the header stamps in seconds and nanoseconds? "
                            "(milliseconds read as seconds put a 10 Hz tracker's messages 100 "
                            "s apart)") from None
                    logger.warning(
                        "%s (stamp %.3f s) skipped: it comes %.3f s after the last frame, more "
                        "than the stream's max_gap_s (%g s); the next message within %g s of it "
                        "starts the tracks afresh", where, frame.time_s, gap.gap_s, gap.max_gap_s,
                        gap.max_gap_s)
                except DataError as error:
                    raise DataError(f"{where} (stamp {frame.time_s:.3f} s): {error}") from None
                else:
                    paths, discs = prediction_markers(output, names.names_of(output.ids),
                                                      frame.header)
                    writer.write(PREDICTIONS_TOPIC, paths, log_time)
                    if discs is not None:
                        writer.write(DISCS_TOPIC, discs, log_time)
                        discs_written += len(discs["markers"]) - 1       # less the DELETEALL
                    frames, predictions = frames + 1, predictions + len(output.ids)
                if progress is not None and total:
                    progress.count("frames", frames + skipped, total, started)
            writer.finish()
        os.replace(partial, out)
    finally:
        partial.unlink(missing_ok=True)
    return {"bag": str(source), "out": str(out), "topic": topic, "frame_id": frame_id,
            "frames": frames, "people": len(names.names), "predictions": predictions,
            "discs": discs_written, "skipped": skipped, "topics": dict(writer.counts),
            "seconds": round(time.perf_counter() - started, 3)}


@contextlib.contextmanager
def _refusals_reported_here():
    """The stream's own log records of the frames it refuses (stream_time's errors) kept out of
    the log while a replay runs, in the replay's thread only (other streams of the process log
    theirs): the replay reports each itself, once (the warning of a message it skips, or the
    error it ends on)."""
    replaying = threading.get_ident()

    def unreported(record: logging.LogRecord) -> bool:
        return not (record.module == "stream_time" and record.levelno >= logging.ERROR
                    and record.thread == replaying)

    logger.addFilter(unreported)
    try:
        yield
    finally:
        logger.removeFilter(unreported)


def _same_frame(first: str | None, frame_id: str, where: str) -> str:
    """The frame every message is in: the first message's; another is refused."""
    if first is not None and frame_id != first:
        raise DataError(f"{where}: its frame_id is {frame_id!r}, the earlier ones' {first!r}: "
                        "the stream needs the people in one fixed world frame (transform them "
                        "first)")
    return frame_id


def _checked_bag(path: Path, topic: str) -> int | None:
    """How many messages the bag's summary counts on `topic` (None without a summary), once
    its summary is read and the topic found there; refused in one line otherwise."""
    from mcap.reader import make_reader

    with open(path, "rb") as file, _unreadable_as_data_error(path):
        summary = make_reader(file).get_summary()
    if summary is None:
        return None
    _check_topic(path, topic, {channel.topic: _schema_name(summary.schemas.get(channel.schema_id))
                               for channel in summary.channels.values()})
    if summary.statistics is None:
        return None
    counts = summary.statistics.channel_message_counts
    return sum(counts.get(channel.id, 0) for channel in summary.channels.values()
               if channel.topic == topic)
