"""Make tests/fixtures/torch_checkpoint.pt and .npz: a small file written by torch.save and the
arrays it holds, for `tests/test_safe_loading.py`, which reads it without torch.

    python experiments/torch_fixture.py        # needs torch (a scratch venv will do)

The checkpoint is laid out as the release's and CrowdNav++'s are (an epoch, a
`model_state_dict`, epoch metrics as numpy scalars), its state dict a few tensors that make a
reader honour torch's storage layout: a transposed view and a column sharing one storage
(strides), a slice starting inside its storage (offset), a parameter, a 0-d tensor, float16,
int64 and bool. The .npz holds what `torch.load` returns, as numpy arrays.
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np

FIXTURES = Path(__file__).parents[1] / "tests" / "fixtures"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=FIXTURES / "torch_checkpoint.pt")
    args = parser.parse_args()
    import torch

    weight = torch.arange(12, dtype=torch.float32).reshape(3, 4) / 8 - 0.5
    steps = torch.arange(10, dtype=torch.int64) * 3 - 7
    state_dict = collections.OrderedDict([
        ("linear.weight", weight),
        ("linear.weight_t", weight.t()),                 # stride (1, 4), same storage
        ("linear.column", weight[:, 1]),                 # offset 1, stride (4,)
        ("steps", steps[3:7]),                           # offset 3 into 10 elements
        ("scale", torch.nn.Parameter(torch.tensor([1.5, -2.0]))),
        ("temperature", torch.tensor(0.25)),
        ("half", torch.tensor([[0.5, -1.25]], dtype=torch.float16)),
        ("seen", torch.tensor([True, False, True])),
    ])
    checkpoint = collections.OrderedDict([
        ("epoch", 7), ("model_state_dict", state_dict),
        ("train_loss_epoch", np.float64(-3.77)), ("val_aoe_epoch", np.float32(0.58))])
    torch.save(checkpoint, args.out)

    numpy_scalars = [np._core.multiarray.scalar, np.dtype, type(np.dtype(np.float32)),
                     type(np.dtype(np.float64))]
    with torch.serialization.safe_globals(numpy_scalars):
        loaded = torch.load(args.out, weights_only=True)
    expected = {f"model_state_dict/{name}": value.detach().numpy()
                for name, value in loaded["model_state_dict"].items()}
    expected.update(epoch=np.array(loaded["epoch"]),
                    train_loss_epoch=np.array(loaded["train_loss_epoch"]),
                    val_aoe_epoch=np.array(loaded["val_aoe_epoch"]))
    np.savez(args.out.with_suffix(".npz"), **expected)
    print(f"written: {args.out} ({args.out.stat().st_size} bytes) and its .npz "
          f"(torch {torch.__version__}, numpy {np.__version__})")


if __name__ == "__main__":
    main()
