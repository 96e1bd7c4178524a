"""Make tests/fixtures/crowdnav_parity.npz: CrowdNav++'s own predictor on inputs made here.

    python experiments/crowdnav_fixture.py --crowdnav PATH

PATH is a checkout of CrowdNav++ (github.com/Shuijing725/CrowdNav_Prediction_AttnGraph, MIT
licence, (c) 2021 Zhe Huang for gst_updated/, (c) 2023 Shuijing Liu), holding
`gst_updated/`. Needs torch. For each of its two public checkpoints (`..._seed1000/sj` and
`..._seed1000_rand/sj`), this runs `CrowdNavPredInterfaceMultiEnv.forward` (its code, imported
from PATH, not copied) on the same batch of environments: fully detected humans, humans who
enter late, leave before the last observed step, are seen only at the last two steps, miss
one step in the middle, and padding slots never seen (-999). The fixture holds the inputs,
the outputs (mean mode, `sampling=False`), each checkpoint's weights as numpy arrays and its
`args.pickle` as JSON, so that `tests/test_crowdnav.py` needs neither torch nor CrowdNav++.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from gst_jax.safe_pickle import read_args

CHECKPOINTS = {
    "seed1000": "100-gumbel_social_transformer-faster_lstm-lr_0.001-init_temp_0.5-edge_head_0-"
                "ebd_64-snl_1-snh_8-seed_1000/sj",
    "seed1000_rand": "100-gumbel_social_transformer-faster_lstm-lr_0.001-init_temp_0.5-"
                     "edge_head_0-ebd_64-snl_1-snh_8-seed_1000_rand/sj",
}
MISSING = -999.0
# Its checkpoints were pickled under numpy 1, whose module names numpy 2 has moved.
NUMPY_SCALARS = [((np._core if hasattr(np, "_core") else np.core).multiarray.scalar,
                  "numpy.core.multiarray.scalar"), np.dtype, type(np.dtype(np.float32)),
                 type(np.dtype(np.float64))]


def make_inputs(num_env: int = 4, num_humans: int = 8, obs_len: int = 5, step_s: float = 0.25,
                seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(n_env, N, obs_len, 2) positions (-999 where not detected) and (n_env, N, obs_len, 1)
    masks, as CrowdNav++ hands them to its predictor."""
    rng = np.random.default_rng(seed)
    velocity = rng.normal(0.0, 0.8, (num_env, num_humans, 1, 2))
    start = rng.uniform(-4.0, 4.0, (num_env, num_humans, 1, 2))
    wobble = rng.normal(0.0, 0.03, (num_env, num_humans, obs_len, 2))
    positions = start + velocity * step_s * np.arange(obs_len)[:, None] + wobble
    mask = np.ones((num_env, num_humans, obs_len))
    mask[:, 3, :2] = 0                # enters late
    mask[:, 4, -1] = 0                # leaves before the last observed step
    mask[:, 5, :-2] = 0               # seen at the last two steps only
    mask[:, 6, 2] = 0                 # missed once in the middle (CrowdNav++'s mask quirk)
    mask[:, 7] = 0                    # a padding slot
    mask[-1, 2:] = 0                  # the last environment has only two humans
    positions = np.where(mask[..., None] > 0, positions, MISSING)
    return positions.astype(np.float32), mask[..., None].astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--crowdnav", required=True, type=Path,
                        help="a CrowdNav++ checkout (the folder holding gst_updated/)")
    parser.add_argument("--out", type=Path, default=Path(__file__).parents[1] / "tests"
                        / "fixtures" / "crowdnav_parity.npz")
    args = parser.parse_args()
    sys.path.insert(0, str(args.crowdnav.absolute()))    # its code, run from its checkout
    import torch
    from gst_updated.scripts.wrapper.crowd_nav_interface_parallel import (
        CrowdNavPredInterfaceMultiEnv,
    )

    torch.set_num_threads(1)
    input_traj, input_mask = make_inputs()
    arrays = {"input_traj": input_traj, "input_mask": input_mask}
    for name, folder in CHECKPOINTS.items():
        load_path = args.crowdnav / "gst_updated" / "results" / folder
        # Read without running what it names; CrowdNav++'s own code reads the .pt with
        # torch's weights-only loading.
        model_args = argparse.Namespace(**read_args(load_path / "checkpoint" / "args.pickle"))
        # Its checkpoints hold numpy scalars (epoch metrics), which torch >= 2.6 loads only
        # when allowed by name.
        with torch.serialization.safe_globals(NUMPY_SCALARS):
            predictor = CrowdNavPredInterfaceMultiEnv(str(load_path), torch.device("cpu"),
                                                      model_args, num_env=input_traj.shape[0])
        output_traj, output_mask = predictor.forward(torch.from_numpy(input_traj),
                                                     torch.from_numpy(input_mask),
                                                     sampling=False)
        arrays[f"{name}/output_traj"] = output_traj.numpy()
        arrays[f"{name}/output_mask"] = output_mask.numpy()
        arrays[f"{name}/args"] = np.array(json.dumps(vars(model_args)))
        for key, value in predictor.model.state_dict().items():
            arrays[f"{name}/state_dict/{key}"] = value.numpy()
    np.savez_compressed(args.out, **arrays)
    print(f"written: {args.out}")


if __name__ == "__main__":
    main()
