"""Timing the authors' PyTorch release in the same run as ours (its own venv, never ours).

Prepare a copy once (the release needs torch; the instructions ship with the reference copy,
HOW-TO-RUN.md): copy the release to a scratch folder, make a venv with torch 2.13 CPU, numpy,
scipy, tensorboardX and matplotlib, and run its `scripts/create_datasets.py --dataset S` for
every scene you time. Then pass `--release-dir FOLDER --release-python VENV/bin/python` to the
benchmarks. The release's `time_release.py` times training (forward, backward, Adam every 16
windows) over the first K training windows and one-sample inference over the first K test
windows; it prints milliseconds per window and the projected full pass.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

_LINE = re.compile(r"^(?P<scene>\S+) (?P<split>train|test) .*?: (?P<timed>\d+) of (?P<total>\d+) "
                   r"windows, mean N (?P<mean_n>[\d.]+), (?P<ms>[\d.]+) ms/window, projected full "
                   r"pass (?P<projected>[\d.]+) s")


def time_release(release_dir: str, python: str, scene: str, *, windows: int = 64,
                 threads: int = 2) -> dict[str, dict]:
    """{'train': {...}, 'test': {...}}: ms per window, windows timed, projected pass (s)."""
    out = subprocess.run([python, "time_release.py", "--dataset", scene, "--windows",
                          str(windows), "--threads", str(threads)], cwd=Path(release_dir),
                         capture_output=True, text=True, check=True).stdout
    result = {}
    for line in out.splitlines():
        if match := _LINE.match(line.strip()):
            result[match["split"]] = {"ms_per_window": float(match["ms"]),
                                      "windows_timed": int(match["timed"]),
                                      "windows": int(match["total"]),
                                      "mean_n": float(match["mean_n"]),
                                      "projected_s": float(match["projected"])}
    if set(result) != {"train", "test"}:
        raise RuntimeError(f"unexpected output of the release's time_release.py:\n{out}")
    return result
