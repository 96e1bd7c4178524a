"""Reading the pickles of others without running their code, and without torch (numpy only).

`pickle.load` calls whatever a file names, so a crafted checkpoint runs any command. These
readers admit only the globals that such files hold and refuse anything else with a
`DataError` naming the file and the global:

- `read_args(path) -> dict`: a pickled `argparse.Namespace` (CrowdNav++'s
  `checkpoint/args.pickle`) or dict, of plain values.
- `read_torch(path, max_bytes)`: a `torch.save` file in its zip format (torch >= 1.6):
  containers and plain values, `collections.OrderedDict`, tensors and parameters as numpy
  arrays (each a copy, with its storage offset, size and stride, in this machine's byte order),
  torch dtypes as numpy dtypes, and numpy scalars (the release's epoch metrics, pickled under
  numpy 1 as
  `numpy.core.multiarray.scalar`, which numpy 2 names `numpy._core.multiarray.scalar`).

Nor can a file rewire the reader: the admitted globals refuse having their state set (pickle's
BUILD), and numpy dtypes are built as copies, never numpy's shared ones.

Nor can a small file make the reader allocate much: everything `read_torch` allocates for a
file (its pickle, each storage's bytes, each tensor's copy) is counted against `max_bytes`,
and what would pass it is refused in one line BEFORE it is allocated: a zip entry by the size
its header declares (a 4 MB entry that deflates to 4 GiB), a storage by the element count its
pickle names, a tensor by its shape (a 620-byte file holding a (40000, 40000) tensor of stride
0 over one element would be a 6.4 GB copy). Entries are decompressed in bounded chunks and
never past the size their header declares (zipfile's own `read()` would inflate up to 2 GiB
at once first). The default, MAX_BYTES, is for a reader that knows nothing of the file;
`declared_copies` bounds it further by the bytes the zip's own entries declare (a 620-byte
file may then make a few kB, whatever else tells how large its tensors should be):
`gst_jax.crowdnav.load` reads a checkpoint so, within a fixed budget. `read_args` reads at most
MAX_ARGS_BYTES.

One job, though over 400 lines: an unpickler that admits a closed list of globals, and the
bounds on what it allocates, which must see every object it builds.

Nor does either read anything but a regular file within its bound (a FIFO would block the
read, a link to /dev/zero never end it): `gst_jax.regular_files` refuses it unread.
"""

from __future__ import annotations

import collections
import io
import math
import pickle
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from gst_jax.errors import DataError
from gst_jax.regular_files import open_regular, read_regular

# torch's storage classes and dtypes by name, as torch.save writes them; numpy has no bfloat16.
STORAGE_DTYPES = {
    "DoubleStorage": np.float64, "FloatStorage": np.float32, "HalfStorage": np.float16,
    "LongStorage": np.int64, "IntStorage": np.int32, "ShortStorage": np.int16,
    "CharStorage": np.int8, "ByteStorage": np.uint8, "BoolStorage": np.bool_,
    "ComplexFloatStorage": np.complex64, "ComplexDoubleStorage": np.complex128}
TORCH_DTYPES = {
    "float64": np.float64, "float32": np.float32, "float16": np.float16, "int64": np.int64,
    "int32": np.int32, "int16": np.int16, "int8": np.int8, "uint8": np.uint8,
    "uint16": np.uint16, "uint32": np.uint32, "uint64": np.uint64, "bool": np.bool_,
    "complex64": np.complex64, "complex128": np.complex128}
# What reading one .pt may allocate unless its reader knows better (`read_torch(max_bytes=)`):
# CrowdNav++'s checkpoints (parameters, Adam's moments, metrics) make 1.6 MB, the release's less.
MAX_BYTES = 2**30
# The largest args.pickle read: CrowdNav++'s are 741 and 746 bytes.
MAX_ARGS_BYTES = 2**20
# Zip entries are inflated this much at a time.
CHUNK_BYTES = 2**20
ARGS_ALLOWED = "only argparse.Namespace and plain values are allowed"
TORCH_ALLOWED = "only tensors, plain values and numpy scalars are allowed"


class _Refused(Exception):
    """Why a file is refused; the reader prefixes the file's path."""


class _Admitted:
    """An admitted global: callable, and refusing BUILD, which would set its attributes."""

    __slots__ = ("name", "function")

    def __init__(self, name: str, function: Callable):
        self.name = name
        self.function = function

    def __call__(self, *args):
        return self.function(*args)

    def __setstate__(self, state):
        raise _Refused(f"refused to set the state of {self.name}")


class _Namespace:
    """argparse.Namespace as args.pickle holds it: NEWOBJ, then BUILD with its values."""

    def __setstate__(self, state):
        if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
            raise _Refused("an argparse.Namespace whose state is not a dict of names")
        self.values = dict(state)


class _StorageType:
    """A torch storage class (`torch.FloatStorage`, ...), the dtype its bytes hold."""

    __slots__ = ("name", "dtype")

    def __init__(self, name: str, dtype: np.dtype):
        self.name = name
        self.dtype = dtype

    def __setstate__(self, state):
        raise _Refused(f"refused to set the state of {self.name}")


class _Storage:
    """One storage of a .pt file: its bytes, the dtype torch saved them as, their byte order."""

    __slots__ = ("raw", "dtype", "byteorder", "budget")

    def __init__(self, raw: bytes, dtype: np.dtype, byteorder: str, budget: _Budget):
        self.raw = raw
        self.dtype = dtype
        self.byteorder = byteorder
        self.budget = budget    # what reading its file may still allocate, its tensors included

    def values(self, dtype: np.dtype) -> np.ndarray:
        """The storage as a 1-D read-only array of `dtype` in the file's byte order (a view of
        its bytes: nothing is allocated)."""
        stored = np.dtype(dtype).newbyteorder("<" if self.byteorder == "little" else ">")
        return np.frombuffer(self.raw, stored, count=len(self.raw) // stored.itemsize)

    def __setstate__(self, state):
        raise _Refused("refused to set the state of a storage")


class _Budget:
    """What reading one file may still allocate; `take` refuses, before the allocation, what
    would pass it."""

    def __init__(self, max_bytes: int, reason: str):
        self.left, self.max_bytes, self.reason = max_bytes, max_bytes, reason

    def take(self, nbytes: int, what: str):
        if nbytes > self.left:
            raise _Refused(f"{what} would take {_size(nbytes)}, more than the "
                           f"{_size(self.max_bytes)} reading one file may allocate "
                           f"({self.reason}): refused before allocating it")
        self.left -= nbytes


def _size(nbytes: int) -> str:
    """A byte count in words: '6.4 GB' (a count from a crafted file may be any integer)."""
    if nbytes.bit_length() > 64:
        return f"2^{nbytes.bit_length() - 1} bytes or more"
    for unit, scale in (("GB", 10**9), ("MB", 10**6), ("kB", 10**3)):
        if nbytes >= scale:
            return f"{nbytes / scale:.3g} {unit}"
    return f"{nbytes} bytes"


def _read_entry(archive: zipfile.ZipFile, name: str, nbytes: int | None, budget: _Budget
                ) -> bytes:
    """The first `nbytes` (None: all) of a zip entry, checked against the budget by the size
    its header declares before anything is read, inflated at most CHUNK_BYTES at a time and
    never past that size (where the data would go on, zipfile stops and its CRC check fails)."""
    declared = archive.getinfo(name).file_size
    wanted = declared if nbytes is None else nbytes
    if wanted > declared:
        raise _Refused(f"{name} holds {declared} bytes, fewer than the {wanted} it should")
    budget.take(wanted, f"{name} ({declared} bytes by its zip header)")
    parts, left = [], wanted
    with archive.open(name) as entry:
        while left > 0:
            part = entry.read(min(left, CHUNK_BYTES))
            if not part:
                raise _Refused(f"{name} ends after {wanted - left} of the {wanted} bytes its "
                               "zip header declares")
            parts.append(part)
            left -= len(part)
    return b"".join(parts)


def _ints(value, what: str) -> tuple[int, ...]:
    if not isinstance(value, (tuple, list)) or not all(type(v) is int for v in value):
        raise _Refused(f"a tensor whose {what} is not a tuple of integers")
    return tuple(value)


def _tensor(storage, storage_offset, size, stride, dtype=None) -> np.ndarray:
    """A copy of `storage`'s elements at `storage_offset + sum(index * stride)`, shaped `size`.
    Checked first: as_strided on a crafted stride would read outside the storage, and a stride
    of 0 would make a copy of any size from one element (the budget refuses it)."""
    if not isinstance(storage, _Storage):
        raise _Refused("a tensor not backed by a storage of this file")
    dtype = storage.dtype if dtype is None else dtype
    size, stride = _ints(size, "size"), _ints(stride, "stride")
    if type(storage_offset) is not int or len(size) != len(stride):
        raise _Refused(f"a tensor of size {size} with stride {stride}")
    if storage_offset < 0 or min(size + stride, default=0) < 0:
        raise _Refused(f"a tensor with a negative offset, size or stride ({storage_offset}, "
                       f"{size}, {stride})")
    storage.budget.take(math.prod(size) * dtype.itemsize,
                         f"a tensor of size {size} ({dtype}, stride {stride})")
    if math.prod(size) == 0:
        return np.zeros(size, dtype)
    values = storage.values(dtype)
    last = storage_offset + sum((n - 1) * s for n, s in zip(size, stride))
    if last >= len(values):
        raise _Refused(f"a tensor of size {size}, stride {stride} and offset {storage_offset} "
                       f"beyond its storage of {len(values)} elements")
    strides = tuple(s * values.itemsize for s in stride)
    view = np.lib.stride_tricks.as_strided(values[storage_offset:], size, strides,
                                           writeable=False)
    return view.astype(dtype, order="C")        # this machine's byte order, a copy


def _rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad=False,
                       backward_hooks=None, metadata=None) -> np.ndarray:
    return _tensor(storage, storage_offset, size, stride)


def _rebuild_tensor_v3(storage, storage_offset, size, stride, requires_grad, backward_hooks,
                       dtype, metadata=None) -> np.ndarray:
    """torch's rebuild for dtypes that have no typed storage (uint16, ...): the dtype apart."""
    if not isinstance(dtype, np.dtype) or dtype not in _PLAIN_DTYPES:
        raise _Refused("a tensor whose dtype is not a torch dtype")
    return _tensor(storage, storage_offset, size, stride, dtype)


def _rebuild_parameter(data, requires_grad=False, backward_hooks=None, state=None):
    if not isinstance(data, np.ndarray):
        raise _Refused("a parameter that is not a tensor")
    return data


def _encode(text, encoding="latin1") -> bytes:
    """`_codecs.encode`, with which pickle's protocol 2 stores bytes."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise _Refused("_codecs.encode other than of a str in latin1 (pickled bytes)")
    return text.encode("latin1")


def _numpy_dtype(spec, align=False, copy=True) -> np.dtype:
    # Always a copy: the BUILD that follows sets its byte order, not that of numpy's own.
    if not isinstance(spec, str):
        raise _Refused(f"numpy.dtype({spec!r})")
    dtype = np.dtype(spec, align=bool(align), copy=True)
    if dtype.hasobject:
        raise _Refused(f"numpy.dtype({spec!r}), which holds Python objects")
    return dtype


def _numpy_scalar(dtype, data=None):
    if not isinstance(dtype, np.dtype) or dtype.hasobject or not isinstance(data, bytes) \
            or len(data) != dtype.itemsize:
        raise _Refused("a numpy scalar other than a plain number")
    return np.frombuffer(data, dtype, count=1)[0]


def _admit(table: dict[str, Callable]) -> dict[tuple[str, str], Any]:
    admitted = {}
    for name, f in table.items():
        module, attribute = name.rsplit(".", 1)
        admitted[module, attribute] = _Admitted(name, f)
    return admitted


# Builtins that protocol 2 and 3 pickles name (protocol 2 as `__builtin__`, Python 2's name).
_PLAIN = {**_admit({"builtins.set": set, "builtins.frozenset": frozenset,
                    "builtins.complex": complex, "_codecs.encode": _encode}),
          **_admit({"__builtin__.set": set, "__builtin__.frozenset": frozenset,
                    "__builtin__.complex": complex})}
_ARGS_GLOBALS = {**_PLAIN, ("argparse", "Namespace"): _Namespace}
_TORCH_GLOBALS = {
    **_PLAIN,
    **_admit({"collections.OrderedDict": collections.OrderedDict,
              "torch._utils._rebuild_tensor": _tensor,
              "torch._utils._rebuild_tensor_v2": _rebuild_tensor_v2,
              "torch._utils._rebuild_tensor_v3": _rebuild_tensor_v3,
              "torch._utils._rebuild_parameter": _rebuild_parameter,
              "torch._utils._rebuild_parameter_with_state": _rebuild_parameter,
              "numpy.dtype": _numpy_dtype,
              "numpy.core.multiarray.scalar": _numpy_scalar,
              "numpy._core.multiarray.scalar": _numpy_scalar}),
    **{("torch", name): _StorageType(f"torch.{name}", np.dtype(dtype))
       for name, dtype in STORAGE_DTYPES.items()},
    ("torch.storage", "UntypedStorage"): _StorageType("torch.storage.UntypedStorage",
                                                      np.dtype(np.uint8)),
}
_TORCH_DTYPE_NAMES = {("torch", name): dtype for name, dtype in TORCH_DTYPES.items()}
_PLAIN_DTYPES = frozenset(np.dtype(dtype) for dtype in TORCH_DTYPES.values())


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, admitted: dict, allowed: str, storage: Callable | None = None):
        super().__init__(file)
        self.admitted, self.allowed, self.storage = admitted, allowed, storage

    def find_class(self, module: str, name: str):
        if (module, name) in self.admitted:
            return self.admitted[module, name]
        if self.storage is not None and (module, name) in _TORCH_DTYPE_NAMES:
            return np.dtype(_TORCH_DTYPE_NAMES[module, name], copy=True)
        raise _Refused(f"refused to unpickle {module}.{name} ({self.allowed})")

    def persistent_load(self, pid):
        if self.storage is None:
            raise _Refused(f"refused a persistent id ({self.allowed})")
        return self.storage(pid)


def _read(path: Path, read: Callable[[], Any]):
    """`read()`, its failures as one line naming `path`."""
    try:
        return read()
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except _Refused as refused:
        raise DataError(f"{path}: {refused}") from None
    except DataError:       # not a regular file, or too large (gst_jax.regular_files): said
        raise
    except Exception as error:  # a malformed file can fail anywhere inside pickle or zipfile
        raise DataError(f"{path}: not readable ({type(error).__name__}: {error})") from None


def read_args(path: str | Path) -> dict[str, Any]:
    """The values of a pickled `argparse.Namespace` (or dict) of plain values, as a dict.
    A file of more than MAX_ARGS_BYTES is refused unread."""
    path = Path(path)

    def read():
        raw = read_regular(path, MAX_ARGS_BYTES, "gst_jax.safe_pickle.MAX_ARGS_BYTES")
        loaded = _Unpickler(io.BytesIO(raw), _ARGS_GLOBALS, ARGS_ALLOWED).load()
        if isinstance(loaded, _Namespace):
            return dict(getattr(loaded, "values", {}))
        if isinstance(loaded, dict):
            return loaded
        raise _Refused(f"holds a {type(loaded).__name__}, not an argparse.Namespace")
    return _read(path, read)


def read_torch(path: str | Path, max_bytes: int = MAX_BYTES,
               reason: str = "gst_jax.safe_pickle.MAX_BYTES",
               declared_copies: int | None = None) -> Any:
    """What `torch.load(path, weights_only=True)` returns, with numpy arrays for tensors.
    Refuses, before allocating, what would take reading it past `max_bytes` (its pickle, its
    storages' bytes and its tensors' copies together); `reason` says in the refusal where that
    bound comes from. declared_copies: the bound is at most this many times the bytes its zip
    entries declare (torch.save stores them uncompressed: reading one and copying its tensors
    takes about twice them), where that is less."""
    path = Path(path)

    def read():
        # The file itself within the larger bound (zipfile reads its central directory whole;
        # the entries it reads count against max_bytes).
        with open_regular(path, max(max_bytes, MAX_BYTES), reason if max_bytes > MAX_BYTES
                          else "gst_jax.safe_pickle.MAX_BYTES") as file:
            return read_open(file)

    def read_open(file):
        head = file.read(4)
        if not head.startswith(b"PK"):
            raise _Refused("not a torch file in its zip format: torch.save's legacy format "
                           "(before torch 1.6) is not read; re-save it with a newer torch"
                           if head[:1] == b"\x80" else "not a torch file (no zip archive)")
        with zipfile.ZipFile(file) as archive:
            budget = _Budget(max_bytes, reason)
            if declared_copies is not None:
                declared = sum(entry.file_size for entry in archive.infolist())
                if declared_copies * declared < max_bytes:
                    budget = _Budget(declared_copies * declared, f"{declared_copies} times the "
                                     f"{declared} bytes its zip entries declare")
            pickles = [n for n in archive.namelist()
                       if n.endswith("/data.pkl") and n.count("/") == 1]
            if len(pickles) != 1:
                raise _Refused("not a torch file (no single <archive>/data.pkl)")
            prefix = pickles[0][: -len("data.pkl")]
            names = set(archive.namelist())
            byteorder = "little"
            if prefix + "byteorder" in names:
                byteorder = _read_entry(archive, prefix + "byteorder", None, budget).decode()
            if byteorder not in ("little", "big"):
                raise _Refused(f"unknown byte order {byteorder!r}")
            storages: dict[str, _Storage] = {}

            def storage(pid) -> _Storage:
                if not (isinstance(pid, tuple) and len(pid) == 5
                        and pid[0] in ("storage", b"storage") and isinstance(pid[1], _StorageType)
                        and isinstance(pid[2], str) and type(pid[4]) is int and pid[4] >= 0):
                    raise _Refused(f"refused the persistent id {pid!r} ({TORCH_ALLOWED})")
                _, storage_type, key, _, numel = pid
                if key not in storages:
                    record = prefix + "data/" + key
                    if record not in names:
                        raise _Refused(f"no storage {record}")
                    nbytes = numel * storage_type.dtype.itemsize
                    declared = archive.getinfo(record).file_size
                    if declared < nbytes:
                        raise _Refused(f"storage {record} holds {declared} bytes, fewer than "
                                       f"{numel} of {storage_type.dtype}")
                    raw = _read_entry(archive, record, nbytes, budget)
                    storages[key] = _Storage(raw, storage_type.dtype, byteorder, budget)
                return storages[key]

            data_pkl = _read_entry(archive, pickles[0], None, budget)
            return _Unpickler(io.BytesIO(data_pkl), _TORCH_GLOBALS, TORCH_ALLOWED,
                              storage).load()
    return _read(path, read)
