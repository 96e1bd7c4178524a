"""Write simulated crowds (`gst_jax.simulate.crowds`) as `frame ped x y` files, to train a
planner's predictor on them:

    python experiments/make_sim_crowds.py --out runs/sim_crowds --episodes 40
    python -m gst_jax.train --data runs/sim_crowds --fps 4 --step 0.25 --obs-len 5 --pred-len 5 \\
        --edge-heads 0 --no-ghost --node-dim 64 --encoder-layers 1 --lstm-dim 64 \\
        --temporal faster_lstm --output gaussian

Episode k is seeded with k: the files are the same on every machine. Frame ids count the
simulator's steps (4 per second at 0.25 s); each file is split in time as the paper splits a
scene (80 % train, 20 % test). The bundled sample `data/samples/sim_crowds/` is episode 40,
one the 40 above do not hold (`--first 40 --episodes 1`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gst_jax.simulate.crowds import CrowdConfig, crowd_rows, simulate_crowd


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of the files")
    parser.add_argument("--episodes", type=int, default=40, help="files (default: 40)")
    parser.add_argument("--first", type=int, default=0, help="the first episode (default: 0)")
    parser.add_argument("--duration", type=float, default=CrowdConfig.duration_s,
                        help=f"seconds per episode (default: {CrowdConfig.duration_s:g})")
    parser.add_argument("--step", type=float, default=CrowdConfig.step_s,
                        help=f"seconds per step (default: {CrowdConfig.step_s:g})")
    args = parser.parse_args()
    config = CrowdConfig(duration_s=args.duration, step_s=args.step)
    args.out.mkdir(parents=True, exist_ok=True)
    for episode in range(args.first, args.first + args.episodes):
        positions, detected = simulate_crowd(config, seed=episode)
        path = args.out / f"episode_{episode:03d}.txt"
        path.write_text("\n".join(crowd_rows(positions, detected)) + "\n")
        print(f"written: {path}", flush=True)


if __name__ == "__main__":
    main()
