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
import zipfile
from pathlib import Path

import numpy as np
import pytest

from gst_jax import crowdnav, interop
from gst_jax.errors import DataError
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
    def __init__(self, values: np.ndarray):
        self.values = values


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


def write_pt(path: Path, obj, byteorder: str = "little") -> Path:
    """`obj` (holding `_Tensor`s) as torch.save writes it."""
    storages: dict[int, tuple[str, np.ndarray]] = {}

    class Pickler(pickle.Pickler):
        def persistent_id(self, item):
            if not isinstance(item, _Storage):
                return None
            key, values = storages.setdefault(id(item), (str(len(storages)), item.values))
            return ("storage", STORAGE_CLASSES[values.dtype], key, "cpu", values.size)

    buffer = io.BytesIO()
    Pickler(buffer, protocol=2).dump(obj)
    data = buffer.getvalue()
    for name, module in TORCH_NAMES.items():
        data = data.replace(f"c{__name__}\n{name}\n".encode(), f"c{module}\n{name}\n".encode())
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


def test_crowdnav_load_reads_a_checkpoint_folder_and_predicts_as_crowdnav_does(tmp_path):
    fixture = np.load(FIXTURES / "crowdnav_parity.npz")
    prefix = "seed1000/state_dict/"
    state_dict = collections.OrderedDict(
        (key[len(prefix):], _Tensor.of(fixture[key])) for key in fixture.files
        if key.startswith(prefix))
    args = json.loads(str(fixture["seed1000/args"]))
    folder = tmp_path / "sj" / "checkpoint"
    folder.mkdir(parents=True)
    with open(folder / "args.pickle", "wb") as f:
        pickle.dump(argparse.Namespace(**args), f)            # as CrowdNav++ writes it
    write_pt(folder / f"epoch_{args['num_epochs']}.pt",
             {"epoch": args["num_epochs"], "model_state_dict": state_dict,
              "train_loss_epoch": np.float64(-1.25)})

    assert read_args(folder / "args.pickle") == args
    predictor = crowdnav.load(tmp_path / "sj")
    output_traj, output_mask = predictor(fixture["input_traj"], fixture["input_mask"])
    np.testing.assert_allclose(np.asarray(output_traj), fixture["seed1000/output_traj"],
                               atol=1e-5, rtol=0)
    np.testing.assert_array_equal(np.asarray(output_mask), fixture["seed1000/output_mask"])
