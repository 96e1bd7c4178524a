"""Train the authors' release with its own, unchanged `scripts/train.py`, resumable per 10 epochs.

Run it with the release's Python (a venv with torch; `benchmarks/release.py` says how to prepare
a copy of the release), from anywhere:

    OMP_NUM_THREADS=1 RELEASE_PY experiments/release_train.py --release-dir DIR \
        --flush-denormal --keep parked/release-zara2-p-seed1000 \
        -- --dataset zara2 <the other flags of run/train_sparse.sh>

Everything after `--` goes to the release's argument parser as in its `run/train_sparse.sh`
(drop `--deterministic` for GST (P)). The release saves `epoch_N.pt` (model and Adam state)
every 10 epochs and refuses a result folder that exists; run again, this script starts the
release's own `train()` after the newest such checkpoint: weights and Adam state loaded, the
learning-rate and temperature schedules set to that epoch, the epoch loop starting at N + 1,
torch and numpy reseeded with seed + N (the release saves no RNG state, so a resumed run is a
different draw of the same training, not a replay). `--keep DIR` copies every new checkpoint
there (only the newest is kept) and restores from it when the release's own folder is gone, so
a training can outlive the machine it started on. `--flush-denormal`: see its help and
`docs/benchmarks.md`. Nothing of the release is copied here: its module is imported and the
names it looks up for the model, the two schedules, saving, the result-folder check and the
epoch loop's range are wrapped.
"""

from __future__ import annotations

import argparse
import builtins
import os
import re
import shutil
import sys
from pathlib import Path

EPOCH_FILE = re.compile(r"epoch_(\d+)\.pt$")


def newest_checkpoint(folder: Path) -> tuple[int, Path | None]:
    """(N, path) of the newest epoch_N.pt in `folder`; (0, None) when there is none."""
    found = [(int(m[1]), p) for p in folder.glob("epoch_*.pt") if (m := EPOCH_FILE.search(p.name))]
    return max(found) if found else (0, None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--release-dir", type=Path, required=True,
                        help="a prepared copy of the release (its datasets created)")
    parser.add_argument("--keep", type=Path, default=None,
                        help="folder that keeps the newest checkpoint outside the release's copy")
    parser.add_argument("--flush-denormal", action="store_true",
                        help="flush float32 values below 1.2e-38 to zero, as XLA's CPU runtime "
                             "does (torch.set_flush_denormal): on some CPUs the release's "
                             "training otherwise slows down many times once attention peaks")
    parser.add_argument("release_args", nargs=argparse.REMAINDER,
                        help="-- then the release's own train.py flags")
    ours = parser.parse_args()
    release_dir = ours.release_dir.resolve()
    keep = ours.keep.resolve() if ours.keep else None
    sys.argv = ["train.py", *[a for a in ours.release_args if a != "--"]]
    os.chdir(release_dir)
    sys.path[:0] = [str(release_dir / "scripts"), str(release_dir)]

    import numpy as np
    import torch
    import train as release  # the release's scripts/train.py; its pathhack adds the package
    from src.gumbel_social_transformer import st_model as lstm_model
    from src.mgnn.utils import arg_parse, args2writername

    args = arg_parse()
    if ours.flush_denormal and not torch.set_flush_denormal(True):
        raise SystemExit("this CPU cannot flush denormals (torch.set_flush_denormal)")
    if args.temporal != "lstm":
        raise SystemExit("only the release's LSTM model (run/train_sparse.sh) is supported")
    checkpoint_dir = release_dir / "results" / args2writername(args) / args.dataset / "checkpoint"
    checkpoint_dir.mkdir(parents=True, exist_ok=True)
    epoch, path = newest_checkpoint(checkpoint_dir)
    if keep is not None:
        kept_epoch, kept = newest_checkpoint(keep)
        if kept_epoch > epoch:
            shutil.copy2(kept, checkpoint_dir / kept.name)
            epoch, path = kept_epoch, checkpoint_dir / kept.name
    if epoch >= args.num_epochs:
        print(f"{path} is the last epoch: nothing to train")
        return
    state = torch.load(path, weights_only=False) if path else None
    print(f"resuming after epoch {epoch} from {path}" if path else "starting at epoch 1",
          flush=True)

    def model(*a, **k):
        net = lstm_model.st_model(*a, **k)
        if state:
            net.load_state_dict(state["model_state_dict"])
            torch.manual_seed(args.random_seed + epoch)
            np.random.seed(args.random_seed + epoch)
        return net

    def lr_schedule(optimizer, **k):
        schedule = step_lr_class(optimizer, **k)
        if state:  # Adam's state holds the decayed rate; the schedule only needs its epoch
            optimizer.load_state_dict(state["optimizer_state_dict"])
            schedule.last_epoch = epoch
        return schedule

    def temperature_schedule(*a, **k):
        schedule = temperature_class(*a, **k)
        for _ in range(epoch):
            schedule.step()
        return schedule

    def save(obj, filename, *a, **k):
        torch_save(obj, filename, *a, **k)
        if keep is not None and EPOCH_FILE.search(str(filename)):
            kept = keep / Path(filename).name  # whole before the older one goes: crash-safe
            partial = kept.with_suffix(".partial")
            keep.mkdir(parents=True, exist_ok=True)
            shutil.copy2(filename, partial)
            partial.replace(kept)
            for old in keep.glob("epoch_*.pt"):
                if old != kept:
                    old.unlink()

    step_lr_class, temperature_class = release.StepLR, release.Temp_Scheduler
    torch_save = torch.save
    release.st_model = model
    release.offset_error_square_full_partial = lstm_model.offset_error_square_full_partial
    release.StepLR = lr_schedule
    release.Temp_Scheduler = temperature_schedule
    release.torch.save = save
    # main() refuses an existing result folder; train() then finds its checkpoint folder made
    release.isdir = lambda p: Path(os.path.realpath(p)) == checkpoint_dir
    release.range = lambda start, stop: builtins.range(epoch + 1, stop)  # the epoch loop
    release.main(args)


if __name__ == "__main__":
    main()
