"""A stream saved to a file and read back: what a restarted robot resumes from, its tracks and
its discs warm (`Stream.save`, `Stream.load`).

One safetensors file. Its tensors are the tracks' arrays (`StreamState`: ids, histories,
detections, the conformal score buffer and state, the adaptation state), one per leaf, named
by its path ('track_ids', 'feed/issued', 'regions/thresholds', 'adaptation/stats/0', ...),
and the host's arrays, named HOST_TENSORS + their place in the host's fields
('host/_clock/last_output/futures': the last output, which a frame that reaches no model step
repeats, (L, K, P, 2) in sample mode). Its metadata holds, under "gst_jax.stream", one JSON
object for everything else:

    {"format": "gst_jax.stream/2",     # this layout
     "stream": {"predictor": "GST(config=ModelConfig(...), ...)", "params_sha256": "...",
                "step_s": 0.25, "regions": "Regions(method='dtaci', ...)",
                "adaptation": "None", "robot": false},   # what the tracks are of
     "capacity": 16,                    # the state's slots
     "host": {"frames": 42, "key": {...}, ...,    # the host's own fields (`Stream._KEPT`),
              "_clock": {..., "last_output": {"ids": {"tensor": "host/_clock/last_output/ids"},
                                              ...}}},   # each array a tensor's name
     "sha256": "..."}                   # of everything else in the file (`digest`)

(Format 1 held the host's arrays as JSON lists: in sample mode, 20 futures of 128 tracks
passed MAX_HEADER_BYTES, and the file could not be read back. Its files are refused.)

One file, so that one rename replaces it: a crash while saving leaves the last complete save
(or none), never half a file, nor one save's JSON beside another's arrays. Any safetensors
reader opens it (`safetensors.safe_open(path, "np").metadata()` shows the JSON).

`read` checks, refusing in one line naming the file (`DataError`): that it is a regular file
of at most MAX_FILE_BYTES before opening it (`gst_jax.regular_files`: a FIFO would block the
read, a link to /dev/zero never end it), the header's size before reading it (at most
MAX_HEADER_BYTES), the format, the stream the tracks are of against the loading stream's
(`identity`: the predictor, its parameters' checksum, the time step, the regions, the
adaptation, the robot), the capacity (a bucket size), the file's size against what a state of
that capacity holds before the arrays are read (nothing larger is read), the checksum, every
tensor's name, shape and dtype against an empty state of that capacity, and the values (ids
free or non-negative, each held once; positions finite; detections 0 or 1). The host's fields
are read by their own rules (`Kept`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import safetensors.numpy

from gst_jax.data import bucket_size
from gst_jax.errors import DataError
from gst_jax.model.weights import flatten, flatten_abstract, layout_problems
from gst_jax.regular_files import open_regular
from gst_jax.stream_core import FREE, StreamState

FORMAT = "gst_jax.stream/2"
# The metadata entry of the safetensors header that holds the JSON.
METADATA_KEY = "gst_jax.stream"
# A saved stream's header (tensors' entries and the JSON) is a few kB (30 kB with 128 tracks:
# its arrays are tensors); this bounds what a file can make the reader take before anything
# is checked.
MAX_HEADER_BYTES = 2**20
# What a saved stream may weigh: a state of MAX_CAPACITY slots (4.3 kB each with pred_len 12,
# DtACI and an adaptation: 279 MB) fits; nothing is read from a larger file.
MAX_FILE_BYTES = 2**30
# Far beyond any crowd a robot tracks (and int32 frame indices): what a field may hold.
MAX_CAPACITY = 2**16
MAX_COUNT = 2**31 - 1
FIELDS = ("format", "stream", "capacity", "host", "sha256")
# The host's arrays are the file's tensors of this prefix, the JSON holding {"tensor": NAME}
# in their place.
HOST_TENSORS = "host/"


@dataclasses.dataclass(frozen=True)
class Kept:
    """How the file keeps one of the host's fields: `write(value)` as JSON values, among which
    numpy arrays may stand (each kept as a tensor, `HOST_TENSORS`), and `read(json)` the value
    back (its arrays numpy arrays again) or a ValueError saying what it must be."""

    write: Callable[[Any], Any]
    read: Callable[[Any], Any]


def _count(value):
    if type(value) is not int or not 0 <= value <= MAX_COUNT:
        raise ValueError(f"must be a whole number from 0 to {MAX_COUNT}")
    return value


def _track_ids(value):
    if not (isinstance(value, list)
            and all(type(i) is int and 0 <= i <= MAX_COUNT for i in value)):
        raise ValueError(f"must be a list of track ids (whole numbers from 0 to {MAX_COUNT})")
    return set(value)


def _write_key(key: jax.Array) -> dict:
    return {"impl": str(jax.random.key_impl(key)),
            "data": np.asarray(jax.random.key_data(key)).tolist()}


def _read_key(value) -> jax.Array:
    if not (isinstance(value, dict) and set(value) == {"impl", "data"}
            and isinstance(value["impl"], str) and isinstance(value["data"], list)
            and all(type(i) is int and 0 <= i < 2**32 for i in value["data"])):
        raise ValueError("must be {\"impl\": NAME, \"data\": [uint32, ...]}, a JAX key")
    try:
        return jax.random.wrap_key_data(jnp.array(value["data"], jnp.uint32),
                                        impl=value["impl"])
    except (TypeError, ValueError) as error:
        raise ValueError(f"is not a JAX key ({str(error).splitlines()[0]})") from None


# The host's fields by kind.
COUNT = Kept(int, _count)                                           # frames, restarts, ...
TRACK_IDS = Kept(lambda ids: sorted(int(i) for i in ids), _track_ids)   # a set of ids
KEY = Kept(_write_key, _read_key)                                   # a JAX key


def params_digest(params) -> str | None:
    """SHA-256 of a parameter tree's names, shapes, dtypes and values (None: no parameters,
    a predictor without a model)."""
    if params is None:
        return None
    digest = hashlib.sha256()
    for name, array in sorted(flatten(params).items()):
        digest.update(f"{name}:{array.dtype.str}{list(array.shape)};".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def digest(fields: dict, entries: dict, data: bytes) -> str:
    """SHA-256 of the JSON's fields other than sha256 and the safetensors header's tensor
    entries (names, dtypes, shapes, offsets), each as canonical JSON, then the tensors'
    bytes: everything in the file."""
    canonical = json.dumps([{k: v for k, v in fields.items() if k != "sha256"}, entries],
                           sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(canonical.encode("ascii") + data).hexdigest()


def _split(raw: bytes) -> tuple[dict, bytes]:
    """A safetensors file's header (JSON) and its tensors' bytes."""
    size = int.from_bytes(raw[:8], "little")
    return json.loads(raw[8:8 + size]), raw[8 + size:]


def write(path: str | Path, state: StreamState, identity: dict, host: dict) -> Path:
    """Save a stream's state, the `identity` of what its tracks are of and its host's fields
    (JSON values and numpy arrays, `Kept`) to `path` (its folder made if need be),
    atomically: written beside it, then renamed over it. Returns the path."""
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path} is a folder: name the file to save the stream to")
    tensors = flatten(state)
    arrays: dict[str, np.ndarray] = {}
    host = {name: _as_references(value, HOST_TENSORS + name, arrays)
            for name, value in host.items()}
    assert not set(arrays) & set(tensors), "the host's arrays are named apart from the state's"
    tensors.update(arrays)
    fields = {"format": FORMAT, "stream": identity, "capacity": int(state.capacity),
              "host": host}
    header, data = _split(safetensors.numpy.save(tensors))
    fields["sha256"] = digest(fields, header, data)
    raw = safetensors.numpy.save(tensors, metadata={METADATA_KEY: json.dumps(fields)})
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.",
                                         suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as file:
            file.write(raw)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    _sync_folder(path.parent)
    return path


def _as_references(value, name: str, arrays: dict[str, np.ndarray]) -> Any:
    """`value` (JSON values and numpy arrays) with each array put in `arrays` under its name
    (`name`, the place of `value`, then its keys and indices) and {"tensor": that name} in its
    place."""
    if isinstance(value, np.ndarray):
        arrays[name] = np.ascontiguousarray(value)
        return {"tensor": name}
    if isinstance(value, dict):
        return {key: _as_references(item, f"{name}/{key}", arrays) for key, item in value.items()}
    if isinstance(value, list):
        return [_as_references(item, f"{name}/{k}", arrays) for k, item in enumerate(value)]
    return value


def _as_arrays(value, name: str, arrays: dict[str, np.ndarray],
               refuse: Callable[[str], DataError]) -> Any:
    """`_as_references` undone: each {"tensor": NAME} replaced by that tensor, taken out of
    `arrays`; one that names another place than its own, or a tensor the file lacks (or one
    taken already), refused."""
    if isinstance(value, dict) and set(value) == {"tensor"}:
        if value["tensor"] != name or name not in arrays:
            raise refuse(f"host field {name.removeprefix(HOST_TENSORS)} names tensor "
                         f"{_shown(value['tensor'])}, not one of its own")
        return arrays.pop(name)
    if isinstance(value, dict):
        return {key: _as_arrays(item, f"{name}/{key}", arrays, refuse)
                for key, item in value.items()}
    if isinstance(value, list):
        return [_as_arrays(item, f"{name}/{k}", arrays, refuse) for k, item in enumerate(value)]
    return value


def _sync_folder(folder: Path) -> None:
    """Make a rename in `folder` durable (where the OS lets a folder be opened)."""
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def read(path: str | Path, identity: dict, like: Callable[[int], StreamState],
         kept: dict[str, Kept]) -> tuple[StreamState, dict[str, Any]]:
    """The state (numpy arrays) and the host's fields saved in `path` by a stream whose
    `identity` is this one's, checked (module docstring). like(capacity): an empty state of
    that capacity (`jax.eval_shape` of one will do), what the file must hold; kept: the host's
    fields by name, each read by its `Kept`."""
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path} is a folder: name a file saved by Stream.save")
    try:
        with open_regular(path, MAX_FILE_BYTES, "gst_jax.stream_file.MAX_FILE_BYTES") as file:
            state, host = _read(file, path, identity, like)
    except FileNotFoundError:
        raise DataError(f"{path}: no such file (a stream saved by Stream.save)") from None
    except OSError as error:
        raise DataError(f"{path}: not readable ({error})") from None
    if sorted(host) != sorted(kept):
        missing, unknown = sorted(set(kept) - set(host)), sorted(set(host) - set(kept))
        raise DataError(f"{path}: its host fields are not this gst_jax's ("
                        + (f"no {missing[0]}" if missing else f"unknown {unknown[0][:40]!r}")
                        + "): saved by another version")
    values = {}
    for name, rule in kept.items():
        try:
            values[name] = rule.read(host[name])
        except ValueError as error:
            raise DataError(f"{path}: host field {name} is {_shown(host[name])}: "
                            f"{error}") from None
    return state, values


def _read(file, path: Path, identity: dict, like: Callable[[int], StreamState]
          ) -> tuple[StreamState, dict]:
    def refuse(problem: str):
        return DataError(f"{path}: {problem}")

    prefix = file.read(8)
    size = int.from_bytes(prefix, "little")
    if len(prefix) < 8 or size > MAX_HEADER_BYTES:
        raise refuse(f"not a saved stream (its first 8 bytes say a header of {size} bytes; a "
                     f"saved stream's is at most {MAX_HEADER_BYTES})" if len(prefix) == 8 else
                     f"not a saved stream ({len(prefix)} bytes)")
    header_bytes = file.read(size)
    try:
        header = json.loads(header_bytes)
        fields = json.loads(header["__metadata__"][METADATA_KEY])
    except (ValueError, KeyError, TypeError):
        raise refuse("not a saved stream (no safetensors header with a \"gst_jax.stream\" "
                     "entry: written by Stream.save?)") from None
    if not isinstance(fields, dict) or fields.get("format") != FORMAT:
        found = fields.get("format") if isinstance(fields, dict) else None
        raise refuse(f"format {str(found)[:40]!r}, not {FORMAT!r}: saved by another version "
                     "of gst_jax")
    if sorted(fields) != sorted(FIELDS) or not isinstance(fields["stream"], dict) or not (
            isinstance(fields["host"], dict)):
        raise refuse(f"its JSON must hold exactly the fields {', '.join(FIELDS)} (stream and "
                     f"host objects); it holds {', '.join(map(str, fields))[:120]}")
    _check_identity(fields["stream"], identity, refuse)
    capacity = fields["capacity"]
    if type(capacity) is not int or not 1 <= capacity <= MAX_CAPACITY or (
            bucket_size(capacity) != capacity):
        raise refuse(f"capacity {str(capacity)[:40]} is not one a stream grows to (a bucket "
                     f"size of gst_jax.data.bucket_size, at most {MAX_CAPACITY})")
    expected = {name: (tuple(leaf.shape), np.dtype(leaf.dtype))
                for name, leaf in flatten_abstract(like(capacity)).items()}
    entries = {name: entry for name, entry in header.items() if name != "__metadata__"}
    data_bytes = sum(math.prod(shape) * dtype.itemsize for shape, dtype in expected.values()
                     ) + _host_bytes(entries, refuse)
    total = os.fstat(file.fileno()).st_size
    if total != 8 + size + data_bytes:
        raise refuse(f"{total} bytes, where a stream of {capacity} slots saves "
                     f"{8 + size + data_bytes}: the file is truncated or damaged")
    data = file.read(data_bytes)
    recorded = fields["sha256"]
    found = digest(fields, entries, data)
    if found != recorded:
        raise refuse(f"SHA-256 {found[:16]}... is not the {str(recorded)[:16]}... it records: "
                     "the file is damaged or was edited after it was saved")
    try:
        tensors = safetensors.numpy.load(prefix + header_bytes + data)
    except Exception as error:  # safetensors raises its own error type on a malformed file
        raise refuse(f"not a safetensors file ({error})") from None
    arrays = {name: tensors.pop(name) for name in list(tensors) if name.startswith(HOST_TENSORS)}
    problems = layout_problems(tensors, expected)
    if problems:
        raise refuse(f"not the state of this stream: {'; '.join(problems[:3])}")
    abstract = like(capacity)
    state = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(abstract),
                                         [tensors[name] for name in flatten_abstract(abstract)])
    if (problem := _value_problem(state)) is not None:
        raise refuse(problem)
    host = {name: _as_arrays(value, HOST_TENSORS + name, arrays, refuse)
            for name, value in fields["host"].items()}
    if arrays:
        raise refuse(f"tensor {_shown(next(iter(arrays)))} is no host field's")
    return state, host


def _host_bytes(entries: dict, refuse: Callable[[str], DataError]) -> int:
    """The bytes of the host's tensors among a header's `entries`, as their data offsets say
    (which safetensors checks against their shapes and dtypes, and against each other)."""
    total = 0
    for name, entry in entries.items():
        if not name.startswith(HOST_TENSORS):
            continue
        offsets = entry.get("data_offsets") if isinstance(entry, dict) else None
        if not (isinstance(offsets, list) and len(offsets) == 2
                and all(type(offset) is int for offset in offsets)
                and 0 <= offsets[0] <= offsets[1]):
            raise refuse(f"not a saved stream (tensor {_shown(name)} has no data offsets)")
        total += offsets[1] - offsets[0]
    return total


def _check_identity(saved: dict, identity: dict, refuse: Callable[[str], DataError]) -> None:
    """Refuse tracks of another stream, naming the first setting that differs."""
    for name, value in identity.items():
        if name not in saved:
            raise refuse(f"records no {name} of the stream it was saved from")
        if saved[name] != value:
            raise refuse(f"saved by a stream of {name} {_shown(saved[name], str)}; this one "
                         f"has {_shown(value, str)}: load it into a stream built as that one "
                         "was")
    if unknown := sorted(set(saved) - set(identity)):
        raise refuse(f"records {unknown[0]!r} of its stream, which this gst_jax does not know")


def _shown(value, strings: Callable[[str], str] = repr) -> str:
    """A value as a refusal shows it: short (strings by `strings`: quoted or as written)."""
    written = strings(value) if isinstance(value, str) else repr(value)
    return written if len(written) <= 120 else written[:117] + "..."


def _value_problem(state: StreamState) -> str | None:
    """What is wrong with a state's tracks, in words; None where nothing is."""
    ids = np.asarray(state.track_ids)
    held = ids[ids != FREE]
    if (ids < FREE).any():
        return f"track_ids holds {int(ids.min())}: ids are {FREE} (free) or 0 or more"
    if len(np.unique(held)) != len(held):
        values, counts = np.unique(held, return_counts=True)
        return f"track id {int(values[counts > 1][0])} holds two slots"
    if not np.isfinite(np.asarray(state.positions)).all():
        return "positions holds a NaN or infinite value"
    if not np.isin(np.asarray(state.detected), (0.0, 1.0)).all():
        return "detected holds a value other than 0 and 1"
    return None
