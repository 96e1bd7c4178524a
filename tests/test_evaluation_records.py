"""An evaluation's record is named for its K where K is not the paper's 20 (issue 94): a quick
`--samples 2` run leaves the K = 20 record (published results read it by its name) as it was."""

from __future__ import annotations

import json
from pathlib import Path

from gst_jax import evaluate
from gst_jax.config import DataConfig
from gst_jax.io.workdir import WorkDir

SAMPLE = Path(__file__).parents[1] / "data" / "samples" / "crowd_10hz.txt"


def test_a_quick_evaluation_with_other_samples_keeps_the_k20_record(tmp_path, capsys):
    evaluate.main(["pretrained:hotel_d", "--data", str(SAMPLE), "--fps", "10", "--units", "cm",
                   "--samples", "2", "--no-kde", "--json", "--workdir", str(tmp_path)])
    result = json.loads(capsys.readouterr().out)
    name = f"crowd_10hz-{result['protocol_name']}-test-e{result['epoch']}"
    assert sorted(p.name for p in (tmp_path / "eval").iterdir()) == [f"{name}-k2.json",
                                                                    f"{name}-k2.md"]
    assert json.loads((tmp_path / "eval" / f"{name}-k2.json").read_text()) == result

    # The K = 20 record, as published, is not replaced by another quick look.
    published = tmp_path / "eval" / f"{name}.json"
    published.write_text('{"aoe": 0.5}\n')
    evaluate.main(["pretrained:hotel_d", "--data", str(SAMPLE), "--fps", "10", "--units", "cm",
                   "--samples", "2", "--no-kde", "--json", "--workdir", str(tmp_path)])
    assert published.read_text() == '{"aoe": 0.5}\n'


def test_the_paper_k_keeps_the_names_published_records_have():
    folder = WorkDir("run")
    assert folder.evaluation_path(DataConfig(scene="eth"), "test", 200).name == (
        "eth-paper-test-e200.json")
    assert folder.evaluation_path(DataConfig(scene="eth"), "test", 200, 20).name == (
        "eth-paper-test-e200.json")
    assert folder.evaluation_path(DataConfig(scene="eth"), "val", 7, 5).name == (
        "eth-paper-val-e7-k5.json")
