"""What a stream gives for a frame (`StreamOutput`, what `gst_jax.stream.Stream.step` returns),
read off the slots after the frame's last model step: the tracks predicted now, by id (the
robot left out; `predicted`), or, for a frame that reached no model step, the last one's
predictions again (`repeated`); and the tracks it restarted (`restarted`, logged).
"""

from __future__ import annotations

import logging
from typing import Any, NamedTuple

import numpy as np

from gst_jax import conformal
from gst_jax.stream_core import FREE

logger = logging.getLogger("gst_jax.stream")


class StreamOutput(NamedTuple):
    """One frame's predictions, for the tracks predicted now (detected at both of the last
    two steps): ids (L,), futures (L, P, 2) in mean mode or (L, K, P, 2), and with regions
    the radii of their discs (L, P) (metres, around each predicted step; None without).
    delayed: the scores this frame's observations gave the earlier predictions, with the radii
    issued with them (`conformal.DelayedScores`, (C, P) over the slots), for measuring
    coverage; None without regions. restarted: the ids whose track restarted at this frame,
    seen where their track could not have gone (`Gate`: another person under a recycled id,
    or a tracker's switch).

    With frame times (`Stream.step(..., time=)`): time, the time (s) of the model's step the
    predictions start from (`futures[..., k, :]` is at time + (k + 1) step_s); ticks, the
    model steps this frame reached: 0 where it reached none (the last tick's ids, futures and
    radii again, nothing scored: `repeated`), more than 1 after a gap (delayed: the last
    one's scores). Without: time None, ticks 1.

    fallback: None where the model predicted this frame; else why constant velocity did
    (`FALLBACKS`: "compiling", "overrun", "error"; `Stream`'s deadline_s), each track's last
    displacement repeated, with the radii in force and nothing scored (`delayed` all masked).
    """

    ids: np.ndarray
    futures: np.ndarray
    radii: np.ndarray | None = None
    delayed: conformal.DelayedScores | None = None
    restarted: np.ndarray = np.zeros(0, np.int32)
    time: float | None = None
    ticks: int = 1
    fallback: str | None = None

    @property
    def repeated(self) -> bool:
        """Whether this frame reached no model step: the last step's predictions again."""
        return self.ticks == 0


def predicted(step: tuple, robot: int, mean: bool, restarted: np.ndarray, time: float | None,
              ticks: int, fallback: str | None) -> StreamOutput:
    """The output of a model step (`gst_jax.stream_slots.Slots.advance`'s state, futures
    (K, P, C, 2), predicted (C,), radii (C, P) or None and delayed scores) for the tracks it
    predicted (detected at both of the last two steps), the robot (id `robot`) left out:
    futures (L, P, 2) where `mean`, else (L, K, P, 2). The other fields are StreamOutput's."""
    state, futures, predicted, radii, delayed = step
    track_ids = np.asarray(state.track_ids)
    keep = (predicted > 0) & (track_ids != FREE) & (track_ids != robot)
    futures = np.moveaxis(futures[:, :, keep], 2, 0)                        # (L, K, P, 2)
    return StreamOutput(track_ids[keep], futures[:, 0] if mean else futures,
                        None if radii is None else radii[keep], delayed, restarted, time,
                        ticks, fallback)


def repeated(last: dict[str, Any], scored: tuple[int, int] | None, restarted: np.ndarray,
             time: float, fallback: str | None) -> StreamOutput:
    """A frame that reached no model step (ticks 0): the last step's ids, futures and radii
    again (`last`, as `gst_jax.stream_time.Clock.last_output` keeps them), nothing scored
    (delayed of shape `scored`, (C, P), all masked; None without regions: `scored` None)."""
    delayed = None
    if scored is not None:
        nothing: list[Any] = [np.zeros(scored, np.float32), np.zeros(scored, bool),
                              np.zeros(scored, np.float32)]
        delayed = conformal.DelayedScores(*nothing)
    return StreamOutput(last["ids"], last["futures"], last["radii"], delayed, restarted, time, 0,
                        fallback)


def restarted(steps: list[tuple], before: np.ndarray, robot: int, time: float | None
              ) -> np.ndarray:
    """The ids whose track restarted at a frame, sorted, the robot (id `robot`) left out, and
    logged: `before` (those the frame's raw detections restarted) and those restarted at any of
    its model steps (`steps`, `Slots.advance`'s)."""
    ids = before
    for state, *_ in steps:
        track_ids = np.asarray(state.track_ids)
        ids = np.append(ids, track_ids[np.asarray(state.restarted)])
    ids = np.unique(ids[ids != robot]).astype(np.int32)
    if len(ids):
        logger.info("tracks %s restarted%s: each seen where its track could not have gone "
                    "(another person under a recycled id, or a tracker's switch)",
                    ids.tolist(), "" if time is None else f" at {time:.3f} s")
    return ids
