"""Write a model's sampled futures to a TrajNet++ file:
`python -m gst_jax.predict MODEL --data PATH --out predictions.ndjson`.

MODEL is a work directory (or one of its checkpoints), SWEEP_DIR:MEMBER or pretrained:NAME.
For a TrajNet++ file (scene rows with their primary pedestrians), the file is a submission
TrajNet++'s evaluator pairs scene for scene: each of the file's scenes of the split, in its
order, with its id and frames, and K sampled futures of its primary and of the neighbours the
model predicts (rows with prediction_number and scene_id); the model observes the last 8 of
the scene's 9 observed rows and predicts its 12 scored ones (docs/own-data.md). For other
data, or with --windows, every window of the split gets a scene row, its observed tracks and
K sampled futures of every predicted pedestrian. Positions are metres, frames the data's own
ids. `python -m gst_jax.evaluate --predictions FILE --data PATH` scores such a file (with
TrajNet++'s own figures for a submission); a --windows file with the same seed scores exactly
as `python -m gst_jax.evaluate MODEL` does. A crowd too
large for `--memory-budget` samples in chunks; one that cannot fit in the memory available,
even one sample at a time, is refused in one line before anything is allocated, and so is a
process whose memory limit leaves too little for XLA's compiler. A crowd large enough for
`--candidates` to pay is announced with its expected time and memory before its first batch.
`--out` never replaces the data it reads nor anything but a regular file, and a failure or a
stop leaves no partial file behind.
"""

from __future__ import annotations

from pathlib import Path

from gst_jax import cli
from gst_jax.data.protocols import split_files
from gst_jax.evaluation import write_run_predictions
from gst_jax.io.interrupts import removed_on_forced_exit
from gst_jax.predict import DEFAULT_MEMORY_BUDGET, check_compiler_room
from gst_jax.prediction_files import check_output, partial_path
from gst_jax.progress import Progress
from gst_jax.runs import load_model


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.predict", __doc__, compilation_cache=True)
    parser.add_argument("model", help="a work directory of `python -m gst_jax.train` (or one of "
                        "its checkpoints/<epoch>), SWEEP_DIR:MEMBER, or pretrained:NAME")
    cli.add_data_flags(parser, of_run=True)
    cli.add_sampling_flags(parser)
    parser.add_argument("--out", required=True, help="the prediction file to write (ndjson)")
    cli.add_windows_flag(parser, scoring=False)
    parser.add_argument("--memory-budget", type=cli.positive_float, metavar="GIB",
                        default=DEFAULT_MEMORY_BUDGET / 2 ** 30, help="memory one batch's "
                        "program may use; larger crowds sample in chunks (default: %(default)s)")
    cli.run(predict, parser, argv)


def predict(args) -> None:
    check_compiler_room("python -m gst_jax.predict")         # before anything compiles
    run = load_model(args.model, args.epoch).with_candidates(args.candidates)
    data_config = cli.data_config(args, base=run.data_config)
    out = Path(args.out)
    check_output(out, split_files(data_config, args.split))
    with removed_on_forced_exit(partial_path(out)):
        written = write_run_predictions(run, data_config, args.split, out,
                                        num_samples=args.samples, seed=args.seed,
                                        windows=args.windows, progress=Progress(),
                                        memory_budget_bytes=int(args.memory_budget * 2 ** 30))
    cli.say(f"written: {args.out} ({written.rows} rows: {written.answers}, {data_config.scene}, "
            f"{args.split} split, {args.samples} samples of {run.name})")


if __name__ == "__main__":
    main()
