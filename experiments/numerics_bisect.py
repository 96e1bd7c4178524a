"""Which commits changed a training's numbers? The first epochs' losses of one short training,
commit by commit, under fixed conditions (docs/reproducing.md, "The same answer twice").

    python experiments/numerics_bisect.py d394412 ec1d5b6 HEAD     # fingerprint these commits
    python experiments/numerics_bisect.py d394412..HEAD --bisect   # the commits where it changes

Each commit's `gst_jax/` and `data/` are exported (`git archive`) into a temporary folder and
trained there by its own code, `python -m gst_jax.train --scene eth --epochs 3
--max-train-windows 64` (about a minute each on the 2-core VM), with XLA_FLAGS fixed for every
commit (YNNPACK products only, the setting every commit's code accepts) and the threads the
process is given (pin it with `taskset` to compare with pinned runs). A commit's fingerprint is
its losses, printed with every digit; `--bisect` walks the first-parent commits of a range,
fingerprinting only what a binary search needs, and names each commit after which the
fingerprint changes. Records go to <workdir>/fingerprints.tsv (a commit already there is not
trained again).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

TRAIN = ["-m", "gst_jax.train", "--scene", "eth", "--epochs", "3", "--max-train-windows", "64",
         "--checkpoint-every", "100", "--eval-every", "0"]
XLA_FLAGS = "--xla_cpu_experimental_ynn_fusion_type=dot"


def git(*args: str) -> str:
    return subprocess.run(["git", *args], check=True, capture_output=True, text=True).stdout


def fingerprint(commit: str, records: Path) -> str:
    """The losses of the short training at `commit`, as one string of reprs."""
    sha = git("rev-parse", "--short=10", commit).strip()
    known = dict(line.split("\t", 1) for line in records.read_text().splitlines()) \
        if records.is_file() else {}
    if sha in known:
        return known[sha]
    with tempfile.TemporaryDirectory() as folder:
        archive = subprocess.run(["git", "archive", sha, "gst_jax", "data"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", folder], input=archive, check=True)
        workdir = Path(folder) / "run"
        done = subprocess.run([sys.executable, *TRAIN, "--workdir", str(workdir)], cwd=folder,
                              env={**os.environ, "XLA_FLAGS": XLA_FLAGS},
                              capture_output=True, text=True)
        if done.returncode:
            losses = f"failed ({done.stderr.strip().splitlines()[-1:]})"
        else:
            metrics = (workdir / "metrics.jsonl").read_text().splitlines()
            losses = " ".join(repr(json.loads(line)["loss"]) for line in metrics)
    with open(records, "a") as out:
        out.write(f"{sha}\t{losses}\n")
    print(f"{sha}  {losses}", flush=True)
    return losses


def changes(commits: list[str], records: Path) -> list[str]:
    """The commits (oldest first) whose fingerprint differs from their parent's in `commits`,
    found by binary search on each stretch whose ends differ."""
    found: list[str] = []

    def search(low: int, high: int) -> None:
        if high - low < 2:
            found.append(commits[high])
            return
        middle = (low + high) // 2
        for a, b in ((low, middle), (middle, high)):
            if fingerprint(commits[a], records) != fingerprint(commits[b], records):
                search(a, b)

    if fingerprint(commits[0], records) != fingerprint(commits[-1], records):
        search(0, len(commits) - 1)
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("commits", nargs="+", help="commits, or one range A..B with --bisect")
    parser.add_argument("--bisect", action="store_true",
                        help="search the first-parent commits of the range A..B")
    parser.add_argument("--workdir", default="runs/numerics_bisect",
                        help="folder of the fingerprints.tsv record (default: %(default)s)")
    args = parser.parse_args()
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    records = workdir / "fingerprints.tsv"
    if not args.bisect:
        for commit in args.commits:
            fingerprint(commit, records)
        return
    start, end = args.commits[0].split("..")
    commits = [start] + git("rev-list", "--first-parent", "--reverse",
                            f"{start}..{end}").split()
    found = changes(commits, records)
    print("the fingerprint changes at: " + (", ".join(
        git("log", "-1", "--format=%h %s", c).strip()[:100] for c in found) or "no commit"))


if __name__ == "__main__":
    main()
