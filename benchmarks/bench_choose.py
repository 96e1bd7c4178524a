"""Choosing a shipped model for your data: `python -m gst_jax.pretrained choose` on the bundled
10 Hz sample (every shipped model whose time step fits it, and constant velocity, on its
validation windows, 20 samples each).

    python benchmarks/bench_choose.py                 # the bundled sample, every model
    python benchmarks/bench_choose.py --data FILE --fps 10 --units cm

Two calls of `choose` in one process: the first compiles (its programs counted with
`count_compiles`, a program loaded from the persistent cache included), the second compiles
nothing and is the figure: wall seconds and this process's CPU seconds (every thread), the
target's "compute after compiling". The persistent compilation cache is left as the user's.
"""

from __future__ import annotations

import argparse
import time

from common import print_table, record
from gst_jax.compiles import count_compiles
from gst_jax.config import DataConfig
from gst_jax.data.readers import UNITS
from gst_jax.pretrained import choose
from gst_jax.progress import Progress

SAMPLE = "samples/crowd_10hz.txt"          # a path into the bundled data, found from anywhere


class _Quiet(Progress):
    def line(self, text: str) -> None:
        pass


def time_choice(config: DataConfig, samples: int) -> dict:
    """Seconds (wall and CPU) and compilations of a cold and a warm `choose`."""
    row = {}
    for phase in ("cold", "warm"):
        with count_compiles() as compiles:
            wall, cpu = time.perf_counter(), time.process_time()
            choice = choose.choose(config, num_samples=samples, progress=_Quiet())
            row[f"{phase}_wall_s"] = round(time.perf_counter() - wall, 2)
            row[f"{phase}_cpu_s"] = round(time.process_time() - cpu, 2)
        row[f"{phase}_compiles"] = compiles.count
    row.update(models=sum(len(t.rows) - 1 for t in choice.tables), skipped=len(choice.skipped),
               windows=sum(t.windows for t in choice.tables))
    print(choose.format_choice(choice), "\n")
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=SAMPLE)
    parser.add_argument("--fps", type=float, default=10)
    parser.add_argument("--units", default="cm", choices=tuple(UNITS))
    parser.add_argument("--samples", type=int, default=20)
    args = parser.parse_args()
    config = DataConfig(scene="crowd_10hz" if args.data == SAMPLE else "data",
                        protocol="paper-val", data=args.data, fps=args.fps,
                        scale=UNITS[args.units])
    row = time_choice(config, args.samples)
    print_table([row], list(row))
    record("choose", data=args.data, samples=args.samples, **row)


if __name__ == "__main__":
    main()
