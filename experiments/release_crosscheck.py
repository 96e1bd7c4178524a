"""Score one model by both evaluations: gst_jax's and the authors' release's own `eval.py`.

    python experiments/release_crosscheck.py MODEL --scene zara2 --release-dir DIR

MODEL is a release checkpoint (`.../checkpoint/epoch_200.pt`) or anything `gst_jax.evaluate`
accepts (a run directory, `pretrained:NAME`). The weights go across with
`gst_jax.interop` (`params_from_torch` / `params_to_torch`), then

- gst_jax: `evaluate_run` on the paper split's test windows (K = 20 hard samples, key 0),
  fully detected pedestrians, as `python -m gst_jax.evaluate` does;
- the release: its `scripts/eval.py` steps (seeded with 1000, the model built from the same
  flags as its `run/eval_sparse.sh`, then the checkpoint loaded) and its own `inference` in
  test mode: 20 sampled runs at tau 0.03, AOE/FOE and its spread statistic.

Needs torch beside gst_jax (`pip install torch==2.13.0`, the CPU build) and a prepared copy
of the release with the scene's datasets created (`benchmarks/release.py` says how). Only
the release's LSTM GST with n = 1 and the ghost, as its `run/train_sparse.sh` trains it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import re
import sys
from pathlib import Path

import numpy as np

from gst_jax import interop
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.evaluation import evaluate_run
from gst_jax.progress import Progress
from gst_jax.runs import Run, load_model

RELEASE_SEED = 1000  # run/eval_sparse.sh's random_seed, which eval.py seeds torch with


def release_flags(scene: str, config: ModelConfig) -> list[str]:
    """The release's argparse flags for `config`, as `run/eval_sparse.sh` passes them."""
    flags = ["--spatial", "gumbel_social_transformer", "--temporal", "lstm", "--lr", "1e-3",
             "--dataset", scene, "--num_epochs", "200", "--detach_sample",
             "--rotation_pattern", "random", "--spatial_num_heads", str(config.encoder_heads),
             "--spatial_num_layers", str(config.encoder_layers), "--decode_style", "recursive",
             "--spatial_num_heads_edges", str(config.num_edge_heads),
             "--random_seed", str(RELEASE_SEED), "--lstm_hidden_size", str(config.lstm_hidden),
             "--embedding_size", str(config.node_dim), "--batch_size", "16", "--init_temp", "0.5"]
    flags += ["--ghost"] if config.ghost else []
    flags += ["--deterministic"] if config.output == "deterministic" else []
    return flags


def load_either(model: str, scene: str, output: str) -> tuple[Run, dict[str, np.ndarray]]:
    """(the model as a gst_jax run, its weights in the release's names)."""
    if model.endswith(".pt"):
        state_dict = interop.load_state_dict(model)
        node_dim = state_dict["node_embedding.weight"].shape[0]
        config = ModelConfig(node_dim=node_dim, edge_dim=state_dict["edge_embedding.weight"]
                             .shape[0], num_edge_heads=1, ghost=True, output=output)
        params = interop.params_from_torch(state_dict, num_edge_heads=1, ghost=True,
                                           config=config)
        epoch = int(match[1]) if (match := re.search(r"epoch_(\d+)\.pt$", model)) else 0
        run = Run(name=model, model_config=config, data_config=DataConfig(scene=scene),
                  train_config=TrainConfig(), params=params, epoch=epoch, workdir=None)
        return run, state_dict
    run = load_model(model)
    if (run.model_config.temporal, run.model_config.num_edge_heads) != ("lstm", 1):
        raise SystemExit(f"{model}: only the LSTM GST with n = 1 has a release counterpart")
    return run, interop.params_to_torch(run.params, num_edge_heads=1, config=run.model_config)


def release_evaluation(release_dir: Path, scene: str, config: ModelConfig,
                       state_dict: dict[str, np.ndarray]) -> dict[str, float]:
    """The release's test-mode `inference` of its `eval.py`, on `state_dict`."""
    import torch
    sys.path[:0] = [str(release_dir / "scripts"), str(release_dir)]
    sys.argv = ["eval.py", *release_flags(scene, config)]
    import eval as release  # the release's scripts/eval.py
    from src.gumbel_social_transformer.st_model import offset_error_square_full_partial, st_model
    from src.mgnn.utils import arg_parse, load_dataset

    release.offset_error_square_full_partial = offset_error_square_full_partial
    args = arg_parse()
    torch.manual_seed(args.random_seed)          # eval.py's order: seed, data, model, weights
    np.random.seed(args.random_seed)
    loader = load_dataset(args, str(release_dir), subfolder="test")
    model = st_model(args, device="cpu")
    weights = {name: torch.tensor(np.array(value)) for name, value in state_dict.items()}
    missing, unexpected = model.load_state_dict(weights, strict=False)
    if unexpected or any("out_proj" not in name or "edge_selector" not in name for name in missing):
        raise SystemExit(f"weights do not fit the release's model: missing {missing}, "
                         f"unexpected {unexpected}")  # only the selector's unused out_proj may be
    aoe, foe, aoe_spread, foe_spread = release.inference(loader, model, args, mode="test",
                                                         tau=0.03, device="cpu")
    return {"aoe": float(aoe), "foe": float(foe), "aoe_spread": float(aoe_spread),
            "foe_spread": float(foe_spread)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", help="a release epoch_N.pt, a run directory or pretrained:NAME")
    parser.add_argument("--scene", required=True, help="ETH/UCY scene (paper split, test)")
    parser.add_argument("--release-dir", type=Path, required=True,
                        help="a prepared copy of the release, the scene's datasets created")
    parser.add_argument("--output", choices=["gaussian", "deterministic"], default="gaussian",
                        help="GST (P) or (D), for a release checkpoint (default: gaussian)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    args = parser.parse_args()
    run, state_dict = load_either(args.model, args.scene, args.output)
    ours = evaluate_run(run, DataConfig(scene=args.scene), "test", with_kde=False,
                        progress=Progress())
    with contextlib.redirect_stdout(sys.stderr):  # the release prints as it builds its model
        theirs = release_evaluation(args.release_dir.resolve(), args.scene, run.model_config,
                                    state_dict)
    result = {"model": args.model, "scene": args.scene, "node_dim": run.model_config.node_dim,
              "gst_jax": {"aoe": ours["aoe"], "foe": ours["foe"]}, "release": theirs}
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"{args.model} on {args.scene} (paper split, test, 20 runs), d = "
              f"{run.model_config.node_dim}\n"
              f"  gst_jax evaluation:  AOE {ours['aoe']:.4f}  FOE {ours['foe']:.4f}\n"
              f"  release's eval.py:   AOE {theirs['aoe']:.4f}  FOE {theirs['foe']:.4f}  "
              f"spread {theirs['aoe_spread']:.4f} / {theirs['foe_spread']:.4f}")


if __name__ == "__main__":
    main()
