"""experiments/sweep_all.py --layout runs and experiments/_study.py: members trained as runs
(several at once, failures reported), the study tabulated from their evaluations or from
published records, and the paper's three claims judged on paired differences."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

import _common
import _study
import encounters as encounters_script
import gst_jax.evaluate
import gst_jax.train
import sweep_all
from gst_jax.config import Member
from gst_jax.testing.drawn import line_data, pixels_near, saved_figures

ROOT = Path(__file__).parents[1]


def _member(n: int, fully: bool, seed: int, aoe: float) -> dict:
    return {"edge_heads": n, "fully_detected_only": fully, "seed": seed, "aoe": aoe,
            "foe": 2 * aoe}


def test_a_claim_holds_only_where_two_thirds_of_its_pairs_and_every_mean_favour_it():
    results = [{"scene": "eth", "members": [
        _member(0, False, 1, 1.0), _member(0, True, 1, 1.2), _member(4, False, 1, 0.9),
        _member(4, True, 1, 1.1), _member(0, False, 2, 1.0), _member(0, True, 2, 1.1),
        _member(4, False, 2, 1.05), _member(4, True, 2, 1.0)],
        "table": [{"cv_aoe": 0.8, "cv_foe": 1.6}]}]
    encounters = {"scene": "eth", "pairs": [
        {"sparse": "n=4 partial 1", "full": "n=F partial 1",
         "freezing_difference": [-.2, -.3, -.1]},
        {"sparse": "n=4 partial 2", "full": "n=F partial 2", "freezing_difference": [.1, 0, .2]}],
        "models": {"constant velocity": {"freezing_or_u_turn": [0, 0, .01],
                                         "collided": [.5, .4, .6]}}}
    judged = _study.judge_claims(results, encounters)["claims"]
    partial, sparse, freezing = judged["partial"], judged["sparse"], judged["freezing"]
    # partial - full: n=F -0.2, -0.1; n=4 -0.2, +0.05: 3 of 4, both means below 0.
    assert (partial["verdict"], partial["favour"], partial["pairs"]) == ("holds", 3, 4)
    # n=4 - F: partial -0.1, +0.05 (mean -0.025); full -0.1, -0.1: 3 of 4 and every mean.
    assert sparse["verdict"] == "holds"
    assert [m["mean"] for m in sparse["means"]] == pytest.approx([-0.1, -0.025])
    assert freezing["verdict"] == "mixed" and freezing["differences"][0]["edge_heads"] == 4
    results[0]["members"][6]["aoe"] = 1.3          # n=4 partial seed 2 now worse than F
    assert _study.judge_claims(results, None)["claims"]["sparse"]["verdict"] == "mixed"
    for member in results[0]["members"]:           # every sparse member worse
        member["aoe"] += 0.5 * (member["edge_heads"] > 0)
    judged = _study.judge_claims(results, None)
    assert judged["claims"]["sparse"]["verdict"] == "does not hold"
    assert judged["claims"]["freezing"]["verdict"] == "not measured"
    assert "| 2. A sparse interaction graph" in _study.format_claims(judged)


def test_a_members_commands_are_what_train_and_evaluate_accept(monkeypatch, tmp_path):
    """The flags the study passes parse as the commands' own, to the member's settings."""
    seen = {}
    monkeypatch.setattr(gst_jax.train, "train", lambda args: seen.setdefault("train", args))
    monkeypatch.setattr(gst_jax.evaluate, "evaluate",
                        lambda args: seen.setdefault("evaluate", args))
    train, evaluate = _study.member_commands(
        Member(4, True, 1001), "hotel", "paper", 50, "compressed", 5, 3, tmp_path / "m")
    gst_jax.train.main(train[4:])
    gst_jax.evaluate.main(evaluate[4:])
    args = seen["train"]
    assert (args.scene, args.edge_heads, args.seed, args.epochs, args.schedule,
            args.fully_detected_only, args.max_train_windows, args.workdir) == (
        "hotel", 4, 1001, 50, "compressed", True, 3, str(tmp_path / "m"))
    assert (seen["evaluate"].model, seen["evaluate"].samples) == (str(tmp_path / "m"), 5)


def _evaluation(n: int, aoe: float) -> dict:
    """A member's evaluation record: what the study reads of it."""
    return {"aoe": aoe, "foe": 2 * aoe, "cv_aoe": 0.975, "cv_foe": 2.124, "protocol_name": "paper",
            "num_edge_heads": n}


def test_the_study_trains_its_missing_members_as_runs_and_publishes_their_records(
        tmp_path, monkeypatch, capsys):
    """Two members evaluated already; of the two missing, one 'trains' (a stand-in command
    that writes its evaluation) and one fails: the study tabulates three, names the failure,
    and published, reads the records back without the runs."""
    workdir = tmp_path / "study"
    for name, aoe in (("n0-partial-seed1000", 1.0), ("n0-full-seed1000", 1.3)):
        path = _study.evaluation_file(workdir / "eth" / name, "eth", "paper", 200)
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps(_evaluation(0, aoe)))

    def stand_in(member, scene, protocol, epochs, schedule, eval_samples, max_train_windows,
                 workdir):
        path = _study.evaluation_file(workdir, scene, protocol, epochs)
        record = json.dumps(_evaluation(member.edge_heads, 1.1))
        write = (f"import pathlib; p = pathlib.Path({str(path)!r}); "
                 f"p.parent.mkdir(parents=True); p.write_text({record!r})")
        fails = member.fully_detected_only
        return [[sys.executable, "-c", "raise SystemExit(3)" if fails else write]]

    monkeypatch.setattr(_study, "member_commands", stand_in)
    monkeypatch.setattr(_common, "RESULTS", tmp_path / "results")
    (tmp_path / "results" / "runs").mkdir(parents=True)
    argv = ["--scenes", "eth", "--edge-heads", "0,4", "--seeds", "1", "--layout", "runs",
            "--workers", "2", "--encounters", str(tmp_path / "none.json"),
            "--workdir", str(workdir)]
    with saved_figures() as saved:
        sweep_all.main([*argv, "--publish"])
    out = capsys.readouterr().out
    assert "failed, see their logs" in out and "n4-full-seed1000" in out
    study = (tmp_path / "results" / "study.md").read_text()
    assert "| 4 | partial | 1 | 1.100 ± 0.000 | 2.200 ± 0.000 |" in study
    assert "| 2 | eth n=4 partial | 1000 | AOE +0.100, FOE +0.200 m |" in study
    # Fig. 4 draws the three members' errors against n (F, 4): partial detection at n = F
    # and 4, fully detected at F only (its n = 4 failed), constant velocity dashed.
    figure = tmp_path / "results" / "study_fig4_errors_vs_n.png"
    for ax, scale, cv in zip(saved[figure].axes, (1, 2), (0.975, 2.124)):
        [partial] = line_data(ax, "tab:blue")
        np.testing.assert_allclose(partial, [[0, 1.0 * scale], [1, 1.1 * scale]])
        [full] = line_data(ax, "tab:orange")
        np.testing.assert_allclose(full, [[0, 1.3 * scale]])
        [constant_velocity] = line_data(ax, "gray")
        np.testing.assert_allclose(constant_velocity[:, 1], cv)
    assert pixels_near(figure, "tab:blue") > 1_000          # 2,269 here; its legend alone 202
    records = sorted(p.name for p in (tmp_path / "results" / "runs").iterdir())
    assert records == [f"study-eth-{name}-seed1000-e200.json"
                       for name in ("n0-full", "n0-partial", "n4-partial")]

    for path in sorted(workdir.rglob("*"), reverse=True):        # the runs are lost
        path.unlink() if path.is_file() else path.rmdir()
    sweep_all.main([*argv, "--publish", "--tabulate"])
    assert (tmp_path / "results" / "study.md").read_text() == study
    with pytest.raises(SystemExit):
        sweep_all.main([*argv, "--tabulate", "--layout", "sweep"])


def test_an_unfinished_member_parks_and_continues_from_its_parked_copy(tmp_path, monkeypatch):
    """--park keeps a stopped member's newest checkpoint, and a finished member's until the
    encounter record has it; where their work directories are gone (the next sitting's fresh
    checkout) the study restores them from those copies and resumes the unfinished one, and a
    copy goes once its member's record is published."""
    study = tmp_path / "study" / "eth"
    for name, epochs in (("n4-partial-seed1000", (5, 10)), ("n4-partial-seed1001", (200,))):
        for epoch in epochs:
            (study / name / "checkpoints" / str(epoch)).mkdir(parents=True)
            (study / name / "checkpoints" / str(epoch) / "state").write_text(f"weights {epoch}")
        (study / name / "checkpoints" / "checksums.json").write_text("{}")
        (study / name / "config.json").write_text("{}")
    finished = _study.evaluation_file(study / "n4-partial-seed1001", "eth", "paper", 200)
    finished.parent.mkdir()
    finished.write_text(json.dumps(_evaluation(4, 1.2)))
    parked = tmp_path / "parked"
    encounters = tmp_path / "encounters.json"
    argv = ["--scenes", "eth", "--edge-heads", "4", "--seeds", "2", "--fully-detected-only",
            "partial", "--layout", "runs", "--encounters", str(encounters),
            "--workdir", str(tmp_path / "study"), "--parked", str(parked)]
    encounters.write_text(json.dumps({"scene": "eth", "members": ["n=4 partial 1001"]}))
    sweep_all.main([*argv, "--park"])
    assert [p.name for p in parked.iterdir()] == ["study-eth-n4-partial-seed1000-e200"]
    encounters.unlink()      # the finished member's encounters not simulated yet
    sweep_all.main([*argv, "--park"])
    copies = {name: parked / f"study-eth-{name}-e200"
              for name in ("n4-partial-seed1000", "n4-partial-seed1001")}
    assert {name: sorted(str(p.relative_to(copy)) for p in copy.rglob("*") if p.is_file())
            for name, copy in copies.items()} == {
        "n4-partial-seed1000": ["checkpoints/10/state", "checkpoints/checksums.json",
                                "config.json"],
        "n4-partial-seed1001": ["checkpoints/200/state", "checkpoints/checksums.json",
                                "config.json", "eval/eth-paper-test-e200.json"]}
    shutil.rmtree(tmp_path / "study")

    def resumes(member, scene, protocol, epochs, schedule, eval_samples, max_train_windows,
                workdir):
        assert member.seed == 1000      # the finished member is restored, not trained
        state = workdir / "checkpoints" / "10" / "state"
        path = _study.evaluation_file(workdir, scene, protocol, epochs)
        record = json.dumps(_evaluation(member.edge_heads, 1.1))
        return [[sys.executable, "-c",
                 f"import pathlib; assert pathlib.Path({str(state)!r}).read_text() == "
                 f"'weights 10'; p = pathlib.Path({str(path)!r}); "
                 f"p.parent.mkdir(parents=True); p.write_text({record!r})"]]

    monkeypatch.setattr(_study, "member_commands", resumes)
    monkeypatch.setattr(_common, "RESULTS", tmp_path / "results")
    (tmp_path / "results" / "runs").mkdir(parents=True)
    sweep_all.main([*argv, "--publish"])
    for name, copy in copies.items():
        assert (tmp_path / "results" / "runs" / f"study-eth-{name}-e200.json").is_file()
        assert not copy.exists()
    assert list(encounters_script.members(study)) == ["n=4 partial 1000", "n=4 partial 1001"]


def test_the_published_study_is_what_its_command_makes_of_the_records(tmp_path, monkeypatch):
    """results/study.md, remade from a copy of the records in results/runs/ and of
    results/encounters.json by the command docs/reproducing.md names."""
    published = tmp_path / "results"
    (published / "runs").mkdir(parents=True)
    for record in (ROOT / "results" / "runs").glob("study-*.json"):
        shutil.copy2(record, published / "runs")
    shutil.copy2(ROOT / "results" / "encounters.json", published)
    monkeypatch.setattr(_common, "RESULTS", published)
    sweep_all.main(["--scenes", "eth", "--edge-heads", "0,1,4,16", "--layout", "runs",
                    "--tabulate", "--publish", "--workdir", str(tmp_path / "no-runs")])
    assert (published / "study.md").read_text() == (ROOT / "results" / "study.md").read_text()
