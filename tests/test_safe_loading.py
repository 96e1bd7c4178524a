"""Checkpoint files from others are read without torch and never run code (gst_jax.safe_pickle).

tests/fixtures/torch_checkpoint.pt was written by torch.save (torch 2.13, numpy 2.4) and its
.npz holds what torch.load returns: `python experiments/torch_fixture.py` made both. Other
.pt files here are written by `write_pt` in torch's zip layout (`<archive>/data.pkl`, whose
persistent ids name the storages in `<archive>/data/<key>`, and `<archive>/byteorder`); torch
2.13's own `torch.load` reads them to the same arrays.
"""

from __future__ import annotations

import argparse
import collections
import io
import json
import os
import pickle
import re
import struct
import subprocess
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest

from gst_jax import crowdnav, interop
from gst_jax.errors import DataError
from gst_jax.pretrained.__main__ import main as pretrained_main
from gst_jax.safe_pickle import read_args, read_torch

FIXTURES = Path(__file__).parent / "fixtures"
TORCH_FIXTURE = FIXTURES / "torch_checkpoint.pt"


# -- a .pt writer without torch: placeholders pickled as this module's globals, renamed to
# torch's afterwards (protocol 2 writes a global as the text `c<module>\n<name>\n`).
def _rebuild_tensor_v2(*args):
    raise AssertionError("a placeholder for torch._utils._rebuild_tensor_v2")


class FloatStorage:
    """A placeholder for torch.FloatStorage."""


class LongStorage:
    """A placeholder for torch.LongStorage."""


TORCH_NAMES = {"_rebuild_tensor_v2": "torch._utils", "FloatStorage": "torch",
               "LongStorage": "torch"}
STORAGE_CLASSES = {np.dtype(np.float32): FloatStorage, np.dtype(np.int64): LongStorage}


class _Storage:
    def __init__(self, values: np.ndarray, numel: int | None = None):
        self.values = values
        self.numel = values.size if numel is None else numel    # as its pickle names it


class _Tensor:
    """A tensor as torch pickles it: its storage (1-D), offset, size and stride in elements."""

    def __init__(self, storage: _Storage, offset: int, size: tuple, stride: tuple):
        self.storage, self.offset, self.size, self.stride = storage, offset, size, stride

    @classmethod
    def of(cls, array) -> _Tensor:
        array = np.ascontiguousarray(array)
        stride = tuple(s // array.itemsize for s in array.strides)
        return cls(_Storage(array.ravel()), 0, array.shape, stride)

    def __reduce__(self):
        return (_rebuild_tensor_v2, (self.storage, self.offset, self.size, self.stride, False,
                                     collections.OrderedDict()))


def pickled(obj) -> tuple[bytes, dict[int, tuple[str, np.ndarray]]]:
    """`obj`'s data.pkl as torch.save writes it, and its storages {id: (key, values)}."""
    storages: dict[int, tuple[str, np.ndarray]] = {}

    class Pickler(pickle.Pickler):
        def persistent_id(self, item):
            if not isinstance(item, _Storage):
                return None
            key, values = storages.setdefault(id(item), (str(len(storages)), item.values))
            return ("storage", STORAGE_CLASSES[values.dtype], key, "cpu", item.numel)

    buffer = io.BytesIO()
    Pickler(buffer, protocol=2).dump(obj)
    data = buffer.getvalue()
    for name, module in TORCH_NAMES.items():
        data = data.replace(f"c{__name__}\n{name}\n".encode(), f"c{module}\n{name}\n".encode())
    return data, storages


def write_pt(path: Path, obj, byteorder: str = "little") -> Path:
    """`obj` (holding `_Tensor`s) as torch.save writes it."""
    data, storages = pickled(obj)
    order = "<" if byteorder == "little" else ">"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("archive/data.pkl", data)
        archive.writestr("archive/byteorder", byteorder)
        archive.writestr("archive/version", "3\n")
        for key, values in storages.values():
            archive.writestr(f"archive/data/{key}",
                             values.astype(values.dtype.newbyteorder(order)).tobytes())
    return path


def write_zip(path: Path, data_pkl: bytes) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("archive/data.pkl", data_pkl)
        archive.writestr("archive/byteorder", "little")
    return path


class RunsACommand:
    """What an attacker pickles: unpickling it runs `touch MARKER`."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


# -- refusing what would run code


def test_a_crafted_args_pickle_is_refused_in_one_line_and_runs_nothing(tmp_path):
    marker = tmp_path / "marker"
    payload = pickle.dumps(RunsACommand(marker))
    pickle.loads(payload)                    # the payload is live: plain pickle runs it
    assert marker.exists()
    marker.unlink()

    folder = tmp_path / "crowdnav" / "checkpoint"
    folder.mkdir(parents=True)
    args_pickle = folder / "args.pickle"
    args_pickle.write_bytes(payload)
    with pytest.raises(DataError) as refused:
        read_args(args_pickle)
    module = os.system.__module__            # posix, where os.system lives
    assert str(refused.value) == (f"{args_pickle}: refused to unpickle {module}.system (only "
                                  "argparse.Namespace and plain values are allowed)")
    # Hidden among a Namespace's values, spelled os.system (protocol 0), through crowdnav.load.
    args_pickle.write_bytes(pickle.dumps(argparse.Namespace(num_epochs=1,
                                                            lr=RunsACommand(marker))))
    with pytest.raises(DataError, match=f"refused to unpickle {module}.system"):
        crowdnav.load(tmp_path / "crowdnav")
    args_pickle.write_bytes(f"cos\nsystem\n(Vtouch {marker}\ntR.".encode())
    with pytest.raises(DataError, match=r"args.pickle: refused to unpickle os.system \(only"):
        crowdnav.load(tmp_path / "crowdnav")
    assert not marker.exists()


def test_a_crafted_pt_is_refused_in_one_line_and_runs_nothing(tmp_path):
    marker = tmp_path / "marker"
    module = os.system.__module__
    top = write_zip(tmp_path / "top.pt", pickle.dumps(RunsACommand(marker), protocol=2))
    inside = write_zip(tmp_path / "inside.pt", pickle.dumps(
        {"model_state_dict": collections.OrderedDict(w=RunsACommand(marker))}, protocol=2))
    for path in (top, inside):
        with pytest.raises(DataError) as refused:
            interop.load_state_dict(path)
        assert str(refused.value) == (f"{path}: refused to unpickle {module}.system (only "
                                      "tensors, plain values and numpy scalars are allowed)")
    assert not marker.exists()


def test_a_file_cannot_rewire_the_reader_nor_read_outside_a_storage(tmp_path):
    # BUILD on an admitted global would set attributes of the reader's own objects.
    rewire = write_zip(tmp_path / "rewire.pt", b"\x80\x02ccollections\nOrderedDict\n"
                                               b"}X\x08\x00\x00\x00__call__Nsb.")
    with pytest.raises(DataError, match="refused to set the state of collections.OrderedDict"):
        read_torch(rewire)
    # A stride beyond its storage: as_strided would read the process's memory.
    storage = _Storage(np.arange(4, dtype=np.float32))
    beyond = write_pt(tmp_path / "beyond.pt", {"w": _Tensor(storage, 0, (3,), (100,))})
    with pytest.raises(DataError, match=r"a tensor of size \(3,\), stride \(100,\) and offset 0 "
                                        "beyond its storage of 4 elements"):
        read_torch(beyond)
    legacy = tmp_path / "legacy.pt"
    legacy.write_bytes(pickle.dumps({"w": 1}, protocol=2))
    with pytest.raises(DataError, match="legacy format .* re-save it with a newer torch"):
        read_torch(legacy)
    with pytest.raises(DataError, match="missing.pt: no such file"):
        read_torch(tmp_path / "missing.pt")


# -- refusing what would allocate far more than the file holds: each runs in a child process
# whose heap is capped (RLIMIT_DATA), so that a reader that allocated what a file asks for
# fails there with a MemoryError instead of taking this machine's memory.

HEAP_CAP = 512 * 2**20
# The child caps its own heap first (a preexec_fn would fork this multithreaded process).
READ_IN_A_CHILD = """
import resource, sys
resource.setrlimit(resource.RLIMIT_DATA, (int(sys.argv[2]), int(sys.argv[2])))
from gst_jax.errors import DataError
from gst_jax.safe_pickle import read_torch
try:
    loaded = read_torch(sys.argv[1])
except DataError as error:
    print("refused:", error)
else:
    print("read:", {k: (v.shape, float(v.sum())) for k, v in loaded.items()})
"""


def read_with_capped_heap(path: Path) -> str:
    """`read_torch(path)` in a child whose heap may not pass HEAP_CAP: its one line."""
    root = Path(__file__).parents[1]
    env = {**os.environ, "PYTHONPATH": str(root), "OPENBLAS_NUM_THREADS": "1"}
    child = subprocess.run([sys.executable, "-c", READ_IN_A_CHILD, str(path), str(HEAP_CAP)],
                           cwd=root, env=env, capture_output=True, text=True)
    assert child.returncode == 0, child.stderr[-2000:]
    return child.stdout.strip()


def deflated_zeros(mebibytes: int) -> bytes:
    """A raw deflate stream of `mebibytes` MiB of zeros, 1,037 bytes a MiB: one block, fully
    flushed so that it starts afresh, repeated (no need to compress gigabytes)."""
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = compressor.compress(bytes(2**20)) + compressor.flush(zlib.Z_FULL_FLUSH)
    assert compressor.compress(bytes(2**20)) + compressor.flush(zlib.Z_FULL_FLUSH) == block
    return block * mebibytes + compressor.flush()


def zip_by_hand(path: Path, entries: list[tuple[str, bytes, int, int, int]]) -> Path:
    """A zip of (name, data as stored, method (0 stored, 8 deflated), CRC-32, size) entries,
    each header saying the size and CRC given, whatever the data inflates to."""
    local, central = b"", b""
    for name, data, method, crc, size in entries:
        header = struct.pack("<HHHHHIII", 20, 0, method, 0, 0x21, crc, len(data), size)
        central += (b"PK\x01\x02" + struct.pack("<H", 20) + header
                    + struct.pack("<HHHHHII", len(name), 0, 0, 0, 0, 0, len(local))
                    + name.encode())
        local += b"PK\x03\x04" + header + struct.pack("<HH", len(name), 0) + name.encode() + data
    end = b"PK\x05\x06" + struct.pack("<HHHHIIH", 0, 0, len(entries), len(entries),
                                       len(central), len(local), 0)
    path.write_bytes(local + central + end)
    return path


def stored(name: str, data: bytes) -> tuple[str, bytes, int, int, int]:
    return name, data, 0, zlib.crc32(data), len(data)


def test_a_zero_stride_tensor_is_refused_before_it_is_copied(tmp_path):
    """620 bytes of .pt holding one float as a (40000, 40000) tensor of stride 0: a 6.4 GB
    copy (issue 74)."""
    one = _Storage(np.zeros(1, np.float32))
    path = write_pt(tmp_path / "stride0.pt", {"w": _Tensor(one, 0, (40000, 40000), (0, 0))})
    assert path.stat().st_size < 1000
    assert read_with_capped_heap(path) == (
        f"refused: {path}: a tensor of size (40000, 40000) (float32, stride (0, 0)) would "
        "take 6.4 GB, more than the 1.07 GB reading one file may allocate "
        "(gst_jax.safe_pickle.MAX_BYTES): refused before allocating it")


def test_a_zip_entry_is_read_no_further_than_its_header_declares_and_the_bound(tmp_path):
    """A 4 MB entry that inflates to 4 GiB was read whole (issue 74). Declared as what it
    inflates to, it is refused by its header; declared as 1 MiB, 1 MiB of it is read, never
    more at once (zipfile's own read() would inflate 2 GiB before cutting)."""
    bomb = deflated_zeros(4095)
    assert len(bomb) < 4.3e6
    numel = 4095 * 2**20 // 4
    data, _ = pickled({"w": _Tensor(_Storage(np.zeros(1, np.float32), numel), 0, (numel,),
                                    (1,))})
    honest = zip_by_hand(tmp_path / "honest.pt", [
        stored("archive/data.pkl", data), stored("archive/byteorder", b"little"),
        ("archive/data/0", bomb, 8, 0, 4095 * 2**20)])
    assert read_with_capped_heap(honest) == (
        f"refused: {honest}: archive/data/0 (4293918720 bytes by its zip header) would take "
        "4.29 GB, more than the 1.07 GB reading one file may allocate "
        "(gst_jax.safe_pickle.MAX_BYTES): refused before allocating it")

    numel = 2**20 // 4
    data, _ = pickled({"w": _Tensor(_Storage(np.zeros(1, np.float32), numel), 0, (numel,),
                                    (1,))})
    lying = zip_by_hand(tmp_path / "lying.pt", [
        stored("archive/data.pkl", data), stored("archive/byteorder", b"little"),
        ("archive/data/0", bomb, 8, zlib.crc32(bytes(2**20)), 2**20)])
    assert read_with_capped_heap(lying) == "read: {'w': ((262144,), 0.0)}"

    # The pickle too: by its header, before it is inflated.
    pickle_bomb = zip_by_hand(tmp_path / "pickle.pt", [
        ("archive/data.pkl", bomb, 8, 0, 4095 * 2**20)])
    assert read_with_capped_heap(pickle_bomb).startswith(
        f"refused: {pickle_bomb}: archive/data.pkl (4293918720 bytes by its zip header) would "
        "take 4.29 GB")


def test_a_caller_bounds_what_a_file_may_make(tmp_path):
    storage = _Storage(np.arange(4, dtype=np.float32))
    path = write_pt(tmp_path / "small.pt", {"a": _Tensor(storage, 0, (4,), (1,)),
                                            "b": _Tensor(storage, 0, (2, 4), (0, 1))})
    loaded = read_torch(path, max_bytes=2000)
    np.testing.assert_array_equal(loaded["b"], [[0, 1, 2, 3], [0, 1, 2, 3]])
    # Its pickle, its 16 bytes of storage, and the 16 + 32 bytes of its two tensors.
    pickle_bytes = zipfile.ZipFile(path).getinfo("archive/data.pkl").file_size
    total = len(b"little") + pickle_bytes + 16 + 16 + 32
    read_torch(path, max_bytes=total)
    with pytest.raises(DataError, match=r"a tensor of size \(2, 4\) \(float32, stride \(0, 1\)\) "
                                        r"would take 32 bytes, more than the \d+ bytes reading "
                                        r"one file may allocate \(the test's\)"):
        read_torch(path, max_bytes=total - 1, reason="the test's")
    # A (numpy) dtype that is not one of torch's is no tensor's (protocol 0, by hand).
    v3 = (b"ctorch._utils\n_rebuild_tensor_v3\n("
          b"(Vstorage\nctorch\nFloatStorage\nV0\nVcpu\nI1\ntQ"      # storage 0, 1 element
          b"I0\n(I1\nt(I1\ntI00\nN"                                 # offset, size, stride, ...
          b"cnumpy\ndtype\n(VV8\ntRtR.")                               # numpy.dtype("V8")
    v3 = zip_by_hand(tmp_path / "v3.pt", [stored("archive/data.pkl", v3),
                                          stored("archive/data/0", bytes(4))])
    with pytest.raises(DataError, match="a tensor whose dtype is not a torch dtype"):
        read_torch(v3)


# -- reading what torch writes


def test_reads_a_file_written_by_torch_to_its_arrays(tmp_path):
    expected = np.load(FIXTURES / "torch_checkpoint.npz")
    loaded = read_torch(TORCH_FIXTURE)
    assert isinstance(loaded, collections.OrderedDict) and loaded["epoch"] == 7
    state_dict = loaded["model_state_dict"]
    assert list(state_dict) == [k.split("/", 1)[1] for k in expected.files if "/" in k]
    for name, value in state_dict.items():
        want = expected[f"model_state_dict/{name}"]
        assert value.dtype == want.dtype and value.shape == want.shape, name
        np.testing.assert_array_equal(value, want, err_msg=name)
        assert value.flags.c_contiguous and value.flags.writeable, name
    np.testing.assert_array_equal(state_dict["linear.weight_t"], state_dict["linear.weight"].T)
    # The epoch metrics are numpy scalars, as the release's checkpoints hold them.
    assert type(loaded["train_loss_epoch"]) is np.float64
    assert loaded["train_loss_epoch"] == expected["train_loss_epoch"]
    assert type(loaded["val_aoe_epoch"]) is np.float32
    assert loaded["val_aoe_epoch"] == expected["val_aoe_epoch"]
    assert interop.load_state_dict(TORCH_FIXTURE).keys() == state_dict.keys()

    # Pickled under numpy 1 (CrowdNav++'s checkpoints), the scalar is numpy.core's.
    numpy1 = tmp_path / "numpy1.pt"
    with zipfile.ZipFile(TORCH_FIXTURE) as source, zipfile.ZipFile(numpy1, "w") as target:
        for name in source.namelist():
            data = source.read(name)
            if name.endswith("/data.pkl"):
                assert b"cnumpy._core.multiarray\nscalar\n" in data
                data = data.replace(b"cnumpy._core.", b"cnumpy.core.")
            target.writestr(name, data)
    assert read_torch(numpy1)["train_loss_epoch"] == expected["train_loss_epoch"]


def test_reads_big_endian_files_and_offsets_into_shared_storages(tmp_path):
    storage = _Storage(np.arange(12, dtype=np.float32) - 5.5)
    steps = np.array([3, -2**40, 7], np.int64)
    saved = {"block": _Tensor(storage, 2, (2, 3), (1, 4)),
             "row": _Tensor(storage, 8, (4,), (1,)), "steps": _Tensor.of(steps)}
    for byteorder in ("little", "big"):
        loaded = read_torch(write_pt(tmp_path / f"{byteorder}.pt", saved, byteorder))
        np.testing.assert_array_equal(loaded["block"], [[-3.5, 0.5, 4.5], [-2.5, 1.5, 5.5]])
        np.testing.assert_array_equal(loaded["row"], [2.5, 3.5, 4.5, 5.5])
        np.testing.assert_array_equal(loaded["steps"], steps)
        assert loaded["steps"].dtype == np.int64 and loaded["steps"].dtype.isnative


# -- CrowdNav++'s checkpoint folder, end to end

PARITY = np.load(FIXTURES / "crowdnav_parity.npz")
ARGS = json.loads(str(PARITY["seed1000/args"]))
STATE_DICT = {key[len("seed1000/state_dict/"):]: PARITY[key] for key in PARITY.files
              if key.startswith("seed1000/state_dict/")}


def crowdnav_folder(root: Path, args: dict = ARGS, state_dict: dict = STATE_DICT,
                    **more) -> Path:
    """A CrowdNav++ checkpoint folder (`root/sj/checkpoint/`: args.pickle, epoch_N.pt) as
    CrowdNav++ writes it; `more` joins the .pt's top-level entries."""
    folder = root / "sj" / "checkpoint"
    folder.mkdir(parents=True)
    with open(folder / "args.pickle", "wb") as f:
        pickle.dump(argparse.Namespace(**args), f)            # as CrowdNav++ writes it
    tensors = collections.OrderedDict((k, _Tensor.of(v)) for k, v in state_dict.items())
    epoch = args.get("num_epochs", 100)
    if type(epoch) is int and 0 < epoch < 10**6:
        write_pt(folder / f"epoch_{epoch}.pt", {"epoch": epoch, "model_state_dict": tensors,
                                                "train_loss_epoch": np.float64(-1.25), **more})
    return root / "sj"


def test_crowdnav_load_reads_a_checkpoint_folder_and_predicts_as_crowdnav_does(tmp_path):
    folder = crowdnav_folder(tmp_path)
    assert read_args(folder / "checkpoint" / "args.pickle") == ARGS
    predictor = crowdnav.load(folder)
    output_traj, output_mask = predictor(PARITY["input_traj"], PARITY["input_mask"])
    np.testing.assert_allclose(np.asarray(output_traj), PARITY["seed1000/output_traj"],
                               atol=1e-5, rtol=0)
    np.testing.assert_array_equal(np.asarray(output_mask), PARITY["seed1000/output_mask"])


@pytest.mark.parametrize("changes, problem", [
    ({"num_epochs": 10**5000}, "num_epochs is an integer of 16610 bits: must be an integer "
                               "from 1 to 1000000"),
    ({"embedding_size": "sixty-four"}, "embedding_size is 'sixty-four': must be an integer "
                                       "from 1 to 4096"),
    ({"obs_seq_len": None}, "has no obs_seq_len, one of gst_updated's args that gst_jax "
                            "reads"),
    ({"spatial_num_heads": 7}, "spatial_num_heads 7 does not divide embedding_size 64"),
    ({"pred_seq_len": 10**6}, "pred_seq_len is 1000000: must be an integer from 1 to 1000"),
    ({"lr": float("nan")}, "lr is nan: must be a finite number in (0, 1000]"),
    ({"ghost": "no"}, "ghost is 'no': must be true or false"),
])
def test_hostile_args_are_refused_in_one_line_naming_file_and_field(tmp_path, changes, problem):
    """A bare ValueError (num_epochs 10**5000), TypeError (a word for a width) or KeyError
    (a field missing) before (issue 74)."""
    args = {k: v for k, v in {**ARGS, **changes}.items() if v is not None}
    folder = crowdnav_folder(tmp_path, args)
    args_pickle = folder / "checkpoint" / "args.pickle"
    with pytest.raises(DataError) as refused:
        crowdnav.load(folder)
    assert str(refused.value) == f"{args_pickle}: {problem}"
    with pytest.raises(DataError, match=re.escape(problem)):
        crowdnav.from_state_dict(STATE_DICT, args)
    # The export command says it in one line too.
    with pytest.raises(SystemExit) as error:
        pretrained_main(["export", str(folder), "--out", str(tmp_path / "out")])
    assert str(error.value) == f"error: {args_pickle}: {problem}"


def _without(name: str) -> dict:
    return {k: v for k, v in STATE_DICT.items() if k != name}


def _nan_at_first(name: str) -> dict:
    broken = STATE_DICT[name].copy()
    broken.flat[0] = np.nan
    return {**STATE_DICT, name: broken}


@pytest.mark.parametrize("state_dict, problem", [
    (_without("lstm.weight_hh_l0"), "has no tensor lstm.weight_hh_l0, which its model reads"),
    ({}, "holds no state dict (a mapping of names to tensors)"),
    ({**STATE_DICT, "lstm.weight_ih_l0": STATE_DICT["lstm.weight_ih_l0"].T.copy()},
     "lstm.weight_ih_l0 is of shape [64, 256], where its model's is [256, 64]"),
    ({**STATE_DICT, "hidden2pos.bias": np.arange(5)},
     "hidden2pos.bias is int64, not a float32 (or float64) tensor"),
    (_nan_at_first("hidden2pos.weight"),
     "hidden2pos.weight holds 1 non-finite value(s) of 320: parameters must be finite"),
])
def test_a_pt_that_is_not_its_models_is_refused_naming_file_and_tensor(tmp_path, state_dict,
                                                                       problem):
    """A .pt missing a key of the model raised a bare KeyError; one of another shape or NaN
    loaded (issue 74)."""
    folder = crowdnav_folder(tmp_path, state_dict=state_dict)
    with pytest.raises(DataError) as refused:
        crowdnav.load(folder)
    assert str(refused.value) == f"{folder / 'checkpoint' / 'epoch_100.pt'}: {problem}"


def in_words(nbytes: int) -> str:
    """A byte count as the refusals write it: '1.09 MB', '2.4 kB', '620 bytes'."""
    for unit, scale in (("GB", 10**9), ("MB", 10**6), ("kB", 10**3)):
        if nbytes >= scale:
            return f"{nbytes / scale:.3g} {unit}"
    return f"{nbytes} bytes"


def declared_bytes(pt: Path) -> int:
    with zipfile.ZipFile(pt) as archive:
        return sum(entry.file_size for entry in archive.infolist())


def test_a_checkpoint_may_allocate_only_what_its_zip_entries_declare(tmp_path):
    """A .pt making far more than its own entries hold is refused before the allocation, even
    below the fixed budget (CrowdNav++'s checkpoint with a 16 MB stride-0 tensor beside it)."""
    one = _Storage(np.zeros(1, np.float32))
    folder = crowdnav_folder(tmp_path, optimizer_state_dict={
        "state": {0: {"exp_avg": _Tensor(one, 0, (2000, 2000), (0, 0))}}})
    pt = folder / "checkpoint" / "epoch_100.pt"
    declared = declared_bytes(pt)
    with pytest.raises(DataError) as refused:
        crowdnav.load(folder)
    assert str(refused.value) == (
        f"{pt}: a tensor of size (2000, 2000) (float32, stride (0, 0)) would take 16 MB, more "
        f"than the {in_words(4 * declared)} reading one file may allocate (4 times the "
        f"{declared} bytes its zip entries declare): refused before allocating it")


# crowdnav.load in a child whose heap is capped, one line per folder.
LOAD_IN_A_CHILD = """
import resource, sys
resource.setrlimit(resource.RLIMIT_DATA, (int(sys.argv[1]), int(sys.argv[1])))
from gst_jax import crowdnav
from gst_jax.errors import DataError
for folder in sys.argv[2:]:
    try:
        crowdnav.load(folder)
    except DataError as error:
        print("refused:", error)
    except MemoryError:
        print("MemoryError")
    else:
        print("loaded")
"""


def test_args_in_range_do_not_raise_what_a_checkpoint_may_allocate(tmp_path):
    """args.pickle and the .pt come from the same folder: with in-range args of 64 layers
    4096 wide, a 620-byte .pt reached 6.46 GB and a 4 MB zip bomb 4.29 GB (issue 94; a 0.3 MB
    bomb of 315 MB here). The bound is the fixed budget and the entries' declared bytes; a
    small .pt of another model is refused by its tensors without allocating the args' model."""
    hostile = {**ARGS, "embedding_size": 4096, "spatial_num_layers": 64}
    assert 4096 % hostile["spatial_num_heads"] == 0
    stride0 = crowdnav_folder(tmp_path / "stride0", hostile, state_dict={})
    one = _Storage(np.zeros(1, np.float32))
    write_pt(stride0 / "checkpoint" / "epoch_100.pt",
             {"model_state_dict": {"w": _Tensor(one, 0, (40000, 40000), (0, 0))}})
    bomb = crowdnav_folder(tmp_path / "bomb", hostile, state_dict={})   # past the budget
    numel = 300 * 2**20 // 4
    data, _ = pickled({"model_state_dict": {"w": _Tensor(
        _Storage(np.zeros(1, np.float32), numel), 0, (numel,), (1,))}})
    zip_by_hand(bomb / "checkpoint" / "epoch_100.pt", [
        stored("archive/data.pkl", data), stored("archive/byteorder", b"little"),
        ("archive/data/0", deflated_zeros(300), 8, 0, 300 * 2**20)])
    small = crowdnav_folder(tmp_path / "small", hostile)
    pts = [folder / "checkpoint" / "epoch_100.pt" for folder in (stride0, bomb, small)]
    assert pts[0].stat().st_size < 1000 and pts[1].stat().st_size < 4e5

    root = Path(__file__).parents[1]
    env = {**os.environ, "PYTHONPATH": str(root), "OPENBLAS_NUM_THREADS": "1"}
    child = subprocess.run([sys.executable, "-c", LOAD_IN_A_CHILD, str(HEAP_CAP), str(stride0),
                            str(bomb), str(small)],
                           cwd=root, env=env, capture_output=True, text=True)
    assert child.returncode == 0, child.stderr[-2000:]
    lines = child.stdout.strip().splitlines()
    declared = declared_bytes(pts[0])
    assert lines[:2] == [
        f"refused: {pts[0]}: a tensor of size (40000, 40000) (float32, stride (0, 0)) would "
        f"take 6.4 GB, more than the {in_words(4 * declared)} reading one file may allocate "
        f"(4 times the {declared} bytes its zip entries declare): refused before allocating it",
        f"refused: {pts[1]}: archive/data/0 (314572800 bytes by its zip header) would take "
        "315 MB, more than the 268 MB reading one file may allocate "
        "(gst_jax.crowdnav.PT_MAX_BYTES): refused before allocating it"], lines
    assert len(lines) == 3 and re.fullmatch(
        rf"refused: {re.escape(str(pts[2]))}: (has no tensor|\S+ is of shape).*", lines[2]), lines
    assert crowdnav.PT_MAX_BYTES == 2**28
