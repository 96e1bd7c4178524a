"""Make `data/samples/crowd_10hz.txt` and `crowd_mot.csv`: the examples of your own data.

    python experiments/make_sample_data.py

The first 60 annotation steps (24 s) of zara1's raw file, pedestrians renumbered from 101,
positions interpolated linearly to 10 Hz (frame ids 0, 1, 2, ... at 10 per second) where a
pedestrian is seen at two consecutive steps, in centimetres. Read with `--fps 10 --units cm`,
it is the original 2.5 Hz data again (every 4th frame is an original annotation).
`crowd_mot.csv` holds those original annotations only, in metres, as MOTChallenge rows
(frame, id, bb_left, bb_top, bb_width, bb_height, conf, x, y, z) under a header, with the
same frame ids: read with `--fps 10` (docs/own-data.md, "Columns").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

ROOT = Path(__file__).parents[1]
SOURCE = ROOT / "data" / "eth_ucy" / "raw" / "zara1" / "crowds_zara01.txt"
OUT = ROOT / "data" / "samples" / "crowd_10hz.txt"
MOT_OUT = OUT.with_name("crowd_mot.csv")
STEPS, UPSAMPLE, SOURCE_STEP = 60, 4, 10


def main() -> None:
    rows = np.loadtxt(SOURCE)
    rows = rows[rows[:, 0] < STEPS * SOURCE_STEP]
    ids = {p: 101 + k for k, p in enumerate(np.unique(rows[:, 1]))}
    lines, annotations = [], []
    for pedestrian, new_id in ids.items():
        track = rows[rows[:, 1] == pedestrian]
        steps = (track[:, 0] // SOURCE_STEP).astype(int)
        for k, (step, xy) in enumerate(zip(steps, track[:, 2:4])):
            lines.append((step * UPSAMPLE, new_id, *xy))
            annotations.append((step * UPSAMPLE, new_id, *xy))
            if k + 1 < len(steps) and steps[k + 1] == step + 1:        # seen at the next step
                for sub in range(1, UPSAMPLE):
                    between = xy + (track[k + 1, 2:4] - xy) * sub / UPSAMPLE
                    lines.append((step * UPSAMPLE + sub, new_id, *between))
    lines.sort()
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text("".join(f"{f}\t{p}\t{100 * x:.2f}\t{100 * y:.2f}\n" for f, p, x, y in lines))
    print(f"written: {OUT} ({len(lines)} rows)")
    annotations.sort()
    MOT_OUT.write_text("frame,id,bb_left,bb_top,bb_width,bb_height,conf,x,y,z\n" + "".join(
        f"{f},{p},-1,-1,-1,-1,1,{x:.4f},{y:.4f},0\n" for f, p, x, y in annotations))
    print(f"written: {MOT_OUT} ({len(annotations)} rows)")


if __name__ == "__main__":
    main()
