"""A stream saved and restored (`Stream.save`, `Stream.load`, `gst_jax.stream_file`): a stream
restored in the middle of a recording steps as one that never stopped, bit for bit (its
discs, drawn from its key, included); a file of another stream, a damaged, edited or truncated
file is refused in one line naming the file; a crash while saving leaves the last save whole.
Constant-velocity streams: nothing to compile but the step, and no model file."""

from __future__ import annotations

import json
import operator
import os
import re

import jax
import numpy as np
import pytest
import safetensors

from gst_jax import stream_file
from gst_jax.adaptation import SpeedScale
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.conformal import Regions
from gst_jax.errors import DataError
from gst_jax.model.gst import init_params
from gst_jax.predictors import ConstantVelocity
from gst_jax.runs import Run
from gst_jax.stream import Stream

STEP_S = 0.4
SAVED_AT = 20


def make(seed: int = 0, capacity: int = 8, **options) -> Stream:
    settings = dict(regions=Regions("dtaci", 0.1), adaptation=SpeedScale(), step_s=STEP_S)
    return Stream(ConstantVelocity(obs_len=8, pred_len=12), seed=seed, capacity=capacity,
                  **{**settings, **options})


def recording(frames: int = 40):
    """Per frame: (ids, positions, time) of noisy walkers, some missed now and then, a crowd
    that grows past 8 after the save point (the capacity grows) and a gap of two steps."""
    rng = np.random.default_rng(7)
    count = 14
    start, velocity = rng.uniform(-5, 5, (count, 2)), rng.uniform(-1.2, 1.2, (count, 2))
    times = STEP_S * np.arange(frames + 1.0)
    times = np.delete(times, 30)                    # frame 30 missing: a gap of 2 steps
    walk = start + velocity * times[:, None, None] + rng.normal(0, 0.05, (len(times), count, 2))
    out = []
    for t in range(frames):
        people = 7 if t < SAVED_AT + 5 else count
        seen = np.flatnonzero(rng.random(people) > 0.15)
        out.append((seen + 100, walk[t, seen], 1000.0 + times[t]))
    return out


def play(player: Stream, frames, forget_at: dict[int, list[int]]):
    outputs = []
    for t, (ids, xy, time) in frames:
        if t in forget_at:
            player.forget(forget_at[t])
        outputs.append(player.step(ids, xy, time=time))
    return outputs


def same(first, second) -> bool:
    """Two streams' outputs equal, bit for bit: ids, futures, radii, delayed scores."""
    return all(np.array_equal(a.ids, b.ids) and np.array_equal(a.futures, b.futures)
               and np.array_equal(a.radii, b.radii) and np.array_equal(a.restarted, b.restarted)
               and all(np.array_equal(x, y) for x, y in zip(a.delayed, b.delayed))
               for a, b in zip(first, second, strict=True))


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A stream that never stopped (its outputs after the save point), and the file it saved at
    frame SAVED_AT with a forget pending (applied at the next step)."""
    frames = list(enumerate(recording()))
    path = tmp_path_factory.mktemp("saved") / "robot" / "stream.safetensors"
    player = make()
    play(player, frames[:SAVED_AT], {12: [101]})
    player.forget([103])
    assert player.save(path) == path
    return path, frames, play(player, frames[SAVED_AT:], {33: [105]}), player


def test_a_restored_stream_steps_as_one_that_never_stopped_bit_for_bit(saved):
    """The restored stream was built with another seed and capacity: the saved key, frame
    count, clock, pending forget and capacity count, not those. A stream of that seed that
    never stopped issues other radii (DtACI draws its expert): the saved key is what makes
    the discs the same."""
    path, frames, never_stopped, player = saved
    restored = make(seed=5, capacity=24).load(path)
    assert restored.frames == SAVED_AT and restored.state.capacity == 8
    after = play(restored, frames[SAVED_AT:], {33: [105]})
    assert same(after, never_stopped)
    assert restored.state.capacity == player.state.capacity == 16 and restored.frames == 41
    assert sum(len(out.ids) for out in after) > 100 and np.isfinite(after[-1].radii).all()
    other_key = play(make(seed=5), frames, {12: [101], SAVED_AT: [103], 33: [105]})
    assert not same(other_key[SAVED_AT:], never_stopped)
    assert same([out._replace(radii=None, delayed=()) for out in other_key[SAVED_AT:]],
                [out._replace(radii=None, delayed=()) for out in never_stopped])


def test_the_file_is_safetensors_with_its_json_in_the_metadata(saved):
    path = saved[0]
    with safetensors.safe_open(path, "np") as file:
        fields = json.loads(file.metadata()[stream_file.METADATA_KEY])
        assert file.get_tensor("track_ids").shape == (8,)
        assert file.get_tensor("regions/thresholds").dtype == np.float32
        last_futures = file.get_tensor("host/_clock/last_output/futures")
    assert fields["host"]["_clock"]["last_output"]["futures"] == {
        "tensor": "host/_clock/last_output/futures"}
    assert last_futures.shape[1:] == (12, 2) and len(last_futures) >= 5
    assert fields["format"] == "gst_jax.stream/2" and fields["capacity"] == 8
    assert fields["host"]["frames"] == SAVED_AT and fields["host"]["_lost"] == [103]
    assert fields["host"]["_clock"]["last_time"] == saved[1][SAVED_AT - 1][1][2]
    assert fields["stream"]["regions"] == repr(Regions("dtaci", 0.1))
    assert fields["stream"]["params_sha256"] is None           # constant velocity: no model


@pytest.mark.parametrize("options, names", [
    (dict(regions=Regions("dtaci", 0.05)), "regions"),
    (dict(adaptation=None), "adaptation"),
    (dict(step_s=0.25), "step_s"),
    (dict(robot=True), "robot"),
])
def test_a_file_of_another_stream_is_refused_naming_what_differs(saved, options, names):
    path = saved[0]
    with pytest.raises(DataError, match=f"^{re.escape(str(path))}: saved by a stream of "
                                        f"{names} .* this one "
                                        "has .*built as that one was$"):
        make(**options).load(path)
    with pytest.raises(DataError, match="saved by a stream of predictor ConstantVelocity"
                                        r"\(obs_len=8, pred_len=12\)"):
        Stream(ConstantVelocity(obs_len=8, pred_len=10), step_s=STEP_S,
               regions=Regions("dtaci", 0.1), adaptation=SpeedScale()).load(path)


def rewritten(path, tmp_path, edit) -> os.PathLike:
    copy = tmp_path / "edited.safetensors"
    copy.write_bytes(edit(path.read_bytes()))
    return copy


@pytest.mark.parametrize("edit, problem", [
    (lambda raw: raw[:-1] + bytes([raw[-1] ^ 1]), "SHA-256 .* is not the .* it records: the "
                                                  "file is damaged or was edited"),
    (lambda raw: raw.replace(b'\\"frames\\": 20', b'\\"frames\\": 21'), "SHA-256"),
    (lambda raw: raw[:-4],
     r"\d+ bytes, where a stream of 8 slots saves \d+: the file is truncated"),
    (lambda raw: (2**40).to_bytes(8, "little") + raw[8:], "not a saved stream .* at most"),
    (lambda raw: b"{}", "not a saved stream \\(2 bytes\\)"),
    (lambda raw: raw.replace(b"gst_jax.stream/2", b"gst_jax.stream/9"),
     "format 'gst_jax.stream/9', not 'gst_jax.stream/2': saved by another version"),
])
def test_a_damaged_edited_or_truncated_file_is_refused_in_one_line(saved, tmp_path, edit,
                                                                   problem):
    path = saved[0]
    copy = rewritten(path, tmp_path, edit)
    with pytest.raises(DataError, match=f"^{re.escape(str(copy))}: {problem}") as refused:
        make().load(copy)
    assert "\n" not in str(refused.value)
    with pytest.raises(DataError, match="no such file"):
        make().load(tmp_path / "none.safetensors")


def test_what_the_checksum_cannot_tell_the_checks_of_the_values_do(saved, tmp_path):
    """A file written with a valid checksum but values no stream holds (by stream_file.write
    itself): a host field out of range, a track id held twice, a capacity no stream grows to."""
    player = saved[3]
    identity = player._identity()
    host = {name: kept.write(operator.attrgetter(attribute)(player))
            for name, (attribute, kept) in Stream._KEPT.items()}
    state = player.state
    cases = [
        (state, {**host, "frames": -3}, "host field frames is -3: must be a whole number"),
        (state, {**host, "key": {"impl": "threefry2x32", "data": [1, 2, 3]}},
         "host field key is .*: is not a JAX key"),
        (state, {k: v for k, v in host.items() if k != "_lost"},
         "its host fields are not this gst_jax's \\(no _lost\\)"),
        (state, {**host, "_clock": {**host["_clock"], "last_output": {
            **host["_clock"]["last_output"], "ids": {"tensor": "host/_clock/last_output/radii"}}}},
         "host field _clock/last_output/ids names tensor 'host/_clock/last_output/radii', not "
         "one of its own"),
        (state.replace(track_ids=np.where(np.asarray(state.track_ids) == 102, 104,
                                          np.asarray(state.track_ids))),
         host, "track id 104 holds two slots"),
        (state.replace(track_ids=state.track_ids[:12], positions=state.positions[:12],
                       detected=state.detected[:12], fresh=state.fresh[:12],
                       restarted=state.restarted[:12]), host,
         "capacity 12 is not one a stream grows to"),
    ]
    assert 102 in np.asarray(state.track_ids) and 104 in np.asarray(state.track_ids)
    for k, (kept_state, kept_host, problem) in enumerate(cases):
        path = stream_file.write(tmp_path / f"{k}.safetensors", kept_state, identity, kept_host)
        with pytest.raises(DataError, match=f"^{re.escape(str(path))}: {problem}"):
            make().load(path)


def test_a_stream_in_sample_mode_saves_its_last_output_as_tensors(tmp_path):
    """20 futures of 24 tracks (a tiny untrained GST: the model is not the point): the last
    output, which a frame between two model steps repeats, is 11,520 numbers; as JSON lists
    in the header (format 1) they made it 238 kB, and with 128 tracks passed MAX_HEADER_BYTES,
    so that the file could not be loaded. Now the header is 5 kB, and the restored stream
    repeats and steps as the saved one, bit for bit."""
    config = ModelConfig(node_dim=8, edge_dim=16, encoder_layers=1, encoder_ff_dim=16,
                         lstm_hidden=8, obs_len=8, pred_len=12)
    run = Run(name="tiny", model_config=config, data_config=DataConfig(),
              train_config=TrainConfig(), params=init_params(config, jax.random.key(0)),
              epoch=0, workdir=None)

    def sampling(seed: int) -> Stream:
        return Stream(run, num_samples=20, mean=False, regions=Regions("dtaci", 0.1), seed=seed)
    rng = np.random.default_rng(3)
    start, velocity = rng.uniform(-10, 10, (24, 2)), rng.uniform(-1, 1, (24, 2))

    def frame(step: float):
        return np.arange(24), start + velocity * step * config.step_s, step * config.step_s
    player = sampling(seed=0)
    for step in range(3):
        *people, time = frame(step)
        last = player.step(*people, time=time)
    assert last.futures.shape == (24, 20, 12, 2)
    path = player.save(tmp_path / "sampling.safetensors")
    header_bytes = int.from_bytes(path.read_bytes()[:8], "little")
    assert header_bytes < 16_000 < 200_000 < len(json.dumps(last.futures.tolist()))
    restored = sampling(seed=5).load(path)
    for step in (2.5, 3):                       # between two model steps (repeated), then at one
        *people, time = frame(step)
        out, never_stopped = restored.step(*people, time=time), player.step(*people, time=time)
        assert out.ticks == never_stopped.ticks == (0 if step == 2.5 else 1)
        assert same([out], [never_stopped])
        if step == 2.5:
            assert np.array_equal(out.futures, last.futures)


def test_a_crash_while_saving_leaves_the_last_save_whole(saved, tmp_path, monkeypatch):
    path = tmp_path / "stream.safetensors"
    path.write_bytes(saved[0].read_bytes())
    player = saved[3]

    def crash(source, target):
        raise OSError("the disk went away")
    monkeypatch.setattr(stream_file.os, "replace", crash)
    with pytest.raises(OSError, match="the disk went away"):
        player.save(path)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stream.safetensors"]
    assert make().load(path).frames == SAVED_AT
    player.save(path)
    assert make().load(path).frames == player.frames != SAVED_AT


def test_saving_to_a_folder_is_refused(tmp_path):
    with pytest.raises(DataError, match="is a folder: name the file"):
        make().save(tmp_path)
    with pytest.raises(DataError, match="is a folder: name a file saved by Stream.save"):
        make().load(tmp_path)
