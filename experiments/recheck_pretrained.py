"""Re-record every shipped model's fixed-key check, after a change to how random draws are
made (e.g. the order of a window's pedestrians):

    python experiments/recheck_pretrained.py

Prints each model's check AOE before and after; `tests/test_pretrained.py` reproduces them.
"""

from __future__ import annotations

import json

from gst_jax import pretrained
from gst_jax.pretrained.export import check_aoe, check_data_config


def recheck(name: str) -> tuple[float, float]:
    """Re-record a shipped model's fixed-key check; returns the old and the new AOE."""
    meta = pretrained.load_meta(name)
    config, params = pretrained.load_pretrained(name)
    old = meta["check"]["aoe"]
    meta["check"]["aoe"] = check_aoe(config, params, check_data_config(meta))
    (pretrained.folder(name) / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return old, meta["check"]["aoe"]


def main() -> None:
    for name in pretrained.available():
        print("{}: check AOE {:.6f} -> {:.6f}".format(name, *recheck(name)))


if __name__ == "__main__":
    main()
