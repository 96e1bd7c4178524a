"""The documentation runs as written: every ```python and ```bash block of README.md and
docs/*.md runs here, from a folder of its own, unless the line `<!-- excerpt: REASON -->` comes
before it, saying why it does not run here (a long training, a cluster, a checkpoint the reader
must bring); excerpts still parse, and every one gives its reason. Also: the README's quick
start prints the table it shows and draws its figure, and an API reference builds from the
docstrings.

A block runs with the interpreter of the test session (as `python3` and `python` for bash
blocks), in a temporary folder holding links to the checkout's data/, experiments/ and
benchmarks/, so that what its commands write (runs/, figures, prediction files) lands there
and not in the checkout. The one substitution: the project's own `pip install` commands are
not rerun (the session runs in the installed project; tests/test_install.py builds and
installs it). A line `... # prints: TEXT` asserts that the block prints TEXT.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from gst_jax import pretrained
from gst_jax.evaluation import format_table
from gst_jax.testing.drawn import pixels_near

ROOT = Path(__file__).parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# A block that does not run here, and why: `<!-- excerpt: trains for 20 minutes -->`.
EXCERPT = re.compile(r"<!-- excerpt: (\S.*?) -->")
EXCERPT_FORM = "<!-- excerpt: why it does not run here -->"
LANGUAGES = {"python": "python", "bash": "bash", "sh": "bash", "shell": "bash"}
LINKED = ("data", "experiments", "benchmarks")       # what blocks read from the checkout
TIMEOUT_S = 300
# The project's own install (`pip install .`, `-e .`, `-e ".[test]"`): already done.
OWN_INSTALL = re.compile(
    r"""python3? -m pip install (-e )?(\.|"\.\[[\w,]+\]"|'\.\[[\w,]+\]')(?=\s|$)""")
PRINTS = re.compile(r"#\s*prints:\s*(.+?)\s*$")

@dataclass(frozen=True)
class Block:
    page: str          # relative to the checkout
    line: int          # of the opening fence
    language: str      # "python", "bash" or "" (untagged)
    code: str
    excerpt: str       # why it does not run here; "" for a block that runs

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"



def blocks(path: Path) -> list[Block]:
    """The fenced blocks of a markdown page, each with the reason of the `<!-- excerpt: ... -->`
    line that comes before its opening fence (blank lines allowed between), if one does."""
    found, lines = [], path.read_text().splitlines()
    k = 0
    while k < len(lines):
        opening = re.match(r"^(\s*)```\s*([\w+-]*)\s*$", lines[k])
        if not opening:
            k += 1
            continue
        indent, language = opening.groups()
        end = next(j for j in range(k + 1, len(lines)) if lines[j].strip() == "```")
        before = next((lines[j].strip() for j in range(k - 1, -1, -1) if lines[j].strip()), "")
        code = "\n".join(line[len(indent):] if line.startswith(indent) else line
                         for line in lines[k + 1:end]) + "\n"
        marker = EXCERPT.fullmatch(before)
        found.append(Block(path.relative_to(ROOT).as_posix(), k + 1, language.lower(), code,
                           marker.group(1) if marker else ""))
        k = end + 1
    return found


ALL = [block for page in DOCS for block in blocks(page)]
CODE = [block for block in ALL if block.language in LANGUAGES]


def _interpreter_folder(tmp: Path) -> Path:
    """python3 and python for bash blocks: this session's interpreter (a wrapper, not a link,
    so that a virtual environment stays one)."""
    folder = tmp / "bin"
    folder.mkdir()
    for name in ("python3", "python"):
        (folder / name).write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
        (folder / name).chmod(0o755)
    return folder


def _run(block: Block, tmp: Path) -> subprocess.CompletedProcess:
    cwd = tmp / "cwd"
    cwd.mkdir()
    for name in LINKED:
        (cwd / name).symlink_to(ROOT / name, target_is_directory=True)
    # XLA as the suite sets it (conftest.py), which serves the blocks' programs to the tests
    # and theirs to the blocks, and is faster for the blocks too: README's quick start took
    # 11.0 s against 13.5 s with a reader's flags, own-data.md's evaluation 14.3 s against
    # 16.6 s (cold caches, 2-core VM, jaxlib 0.10.2).
    env = {**os.environ, "PATH": f"{_interpreter_folder(tmp)}{os.pathsep}{os.environ['PATH']}",
           "MPLBACKEND": "Agg"}
    if LANGUAGES[block.language] == "python":       # tracebacks name the page and line
        command = [sys.executable, "-c",
                   f"exec(compile({block.code!r}, {block.where!r}, 'exec'))"]
    else:
        command = ["bash", "-e", "-o", "pipefail", "-c",
                   OWN_INSTALL.sub(": already installed", block.code)]
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=TIMEOUT_S)


@pytest.fixture(scope="module")
def ran(tmp_path_factory):
    """Each block's run and its folder, once: the test of every block and the checks of what
    a particular block printed or wrote share it."""
    done: dict[Block, tuple[subprocess.CompletedProcess, Path]] = {}

    def run(block: Block) -> tuple[subprocess.CompletedProcess, Path]:
        if block not in done:
            tmp = tmp_path_factory.mktemp("block")
            done[block] = _run(block, tmp), tmp / "cwd"
        return done[block]
    return run


@pytest.mark.parametrize("block", CODE, ids=[block.where for block in CODE])
def test_every_code_block_of_the_docs_runs_or_is_marked_an_excerpt(block, ran):
    if block.excerpt:
        # Not run, but it must still be code: python that compiles, bash that parses.
        if LANGUAGES[block.language] == "python":
            compile(block.code, block.where, "exec")
        else:
            parsed = subprocess.run(["bash", "-n", "-c", block.code], capture_output=True,
                                    text=True)
            assert parsed.returncode == 0, f"{block.where}: {parsed.stderr}"
        return
    try:
        result, _ = ran(block)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{block.where}: the ```{block.language} block ran past {TIMEOUT_S} s; "
                    f"make it smaller or mark it {EXCERPT_FORM}")
    assert result.returncode == 0, (
        f"{block.where}: the ```{block.language} block fails (exit {result.returncode}); fix it "
        f"or mark it {EXCERPT_FORM} (a long training, a cluster, files the reader must "
        f"bring):\n"
        f"{result.stderr[-3000:]}")
    for line in block.code.splitlines():
        if expected := PRINTS.search(line):
            assert expected.group(1) in result.stdout, (
                f"{block.where}: `{line.strip()}` did not print it:\n{result.stdout[-2000:]}")


def test_the_docs_show_commands_only_in_blocks_that_run_or_are_excerpts():
    """An untagged block of commands would escape the test above; a marker must mark a block."""
    untagged = [block.where for block in ALL if not block.language and any(
        re.match(r"\s*(\$ |python3? |bash |srun |sbatch )", line)
        for line in block.code.splitlines())]
    assert not untagged, f"tag these ```bash (or ```python): {untagged}"
    for page in DOCS:
        lines = page.read_text().splitlines()
        markers = sum(bool(EXCERPT.fullmatch(line.strip())) for line in lines)
        marked = sum(bool(block.excerpt) for block in blocks(page))
        assert markers == marked, f"{page.name}: an excerpt marker not before a block"


def test_every_excerpt_says_why_it_does_not_run():
    """A block left out of the run says why, in its marker: `<!-- excerpt -->` alone, or a
    marker the test would not read, is refused."""
    unexplained = [f"{page.relative_to(ROOT)}:{number}" for page in DOCS
                   for number, line in enumerate(page.read_text().splitlines(), 1)
                   if "<!-- excerpt" in line and not EXCERPT.fullmatch(line.strip())]
    assert not unexplained, f"give these their reason, as {EXCERPT_FORM}: {unexplained}"
    reasons = [block.excerpt for block in ALL if block.excerpt]
    assert reasons and all(len(reason.split()) >= 3 for reason in reasons), reasons
    assert not [reason for reason in reasons if "--" in reason], "an HTML comment holds no --"


def test_the_quick_start_prints_the_table_the_readme_shows(ran):
    readme = (ROOT / "README.md").read_text()
    [quick_start] = [block for block in CODE if block.page == "README.md"
                     and "gst_jax.evaluate pretrained:zara1_d" in block.code]
    result, folder = ran(quick_start)
    assert result.returncode == 0, result.stderr[-3000:]
    shown = re.search(r"```\n(model .*?)```", readme, re.S).group(1).splitlines()
    assert [line.split() for line in shown] == [line.split() for line in result.stdout.splitlines()
                                                if line.startswith(("model", "GST ", "constant"))]
    # The figure draws the window: observed (blue) and true (green) paths, predictions (red
    # where fully detected, orange where not), each far beyond its legend's 96 pixels.
    drawn = {colour: pixels_near(folder / "zara1.png", colour)
             for colour in ("tab:blue", "tab:green", "tab:red", "tab:orange")}
    assert drawn["tab:blue"] > 500 and drawn["tab:green"] > 500, drawn
    assert drawn["tab:red"] + drawn["tab:orange"] > 500, drawn


@pytest.fixture(scope="module")
def api_reference(tmp_path_factory) -> tuple[Path, str]:
    """The API reference as the README builds it (folder, pdoc's stderr): once, it imports
    every public module."""
    folder = tmp_path_factory.mktemp("api")
    built = subprocess.run([sys.executable, "-m", "pdoc", "-o", str(folder), "gst_jax"],
                           check=True, capture_output=True, text=True)
    return folder, built.stderr


def test_the_api_reference_builds_from_the_docstrings_without_a_warning(api_reference):
    tmp_path, stderr = api_reference
    assert "Warn" not in stderr, stderr
    pages = {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*.html")}
    assert {"gst_jax.html", "gst_jax/crowdnav.html", "gst_jax/predict.html",
            "gst_jax/config.html", "gst_jax/runs.html", "gst_jax/stream.html",
            "gst_jax/conformal.html", "gst_jax/coverage.html", "gst_jax/simulate.html",
            "gst_jax/simulate/crowdnav/environment.html",
            "gst_jax/simulate/crowdnav/planner.html", "gst_jax/simulate/agents.html"} <= pages
    assert 'id="make_predict"' in (tmp_path / "gst_jax.html").read_text()
    assert 'id="make_predict"' in (tmp_path / "gst_jax" / "predict.html").read_text()
    assert 'id="Predictor"' in (tmp_path / "gst_jax" / "crowdnav.html").read_text()


# What the front pages name: the file formats, their readers and writers, the model's layers.
NAMED_ON_THE_FRONT_PAGE = {
    "gst_jax.data.readers", "gst_jax.data.windows", "gst_jax.data.protocols",
    "gst_jax.prediction_files", "gst_jax.model.weights", "gst_jax.interop", "gst_jax.io.workdir",
    "gst_jax.io.checkpoints", "gst_jax.model.selector", "gst_jax.model.encoder",
    "gst_jax.model.recurrent", "gst_jax.model.temporal", "gst_jax.model.heads",
    "gst_jax.model.layers", "gst_jax.model.gst"}


def _named_modules(text: str, prefix: str = "") -> set[str]:
    """The modules of gst_jax that `text` names (`prefix` + a dotted name, each resolved to its
    longest prefix that is a module; commands run with `python -m` left out)."""
    import importlib.util

    text = re.sub(r"python3?\s+-m\s+gst_jax[\w.]*", "", text)
    pattern = r"\b(gst_jax(?:\.\w+)+)" if not prefix else r"`([a-z_]\w*(?:\.\w+)*)`"
    named = set()
    for name in re.findall(pattern, text):
        parts = (prefix + name).split(".")
        for end in range(len(parts), 0, -1):
            try:
                found = importlib.util.find_spec(".".join(parts[:end])) is not None
            except ModuleNotFoundError:          # a name inside a module: its parent is no package
                found = False
            if found:
                named.add(".".join(parts[:end]))
                break
    return named


def test_the_api_reference_covers_every_module_the_front_pages_name(api_reference):
    """The README and the package's docstring (the reference's first page) name modules; each
    has a page, and its page shows its public functions and classes, not the module's
    internal constants."""
    import gst_jax

    folder, _ = api_reference
    pages = {p.relative_to(folder).with_suffix("").as_posix().replace("/", ".")
             for p in folder.rglob("*.html")}
    named = (_named_modules((ROOT / "README.md").read_text())
             | _named_modules(gst_jax.__doc__ or "", prefix="gst_jax."))
    assert NAMED_ON_THE_FRONT_PAGE <= named, NAMED_ON_THE_FRONT_PAGE - named
    assert not named - pages, f"named on a front page, not in the reference: {named - pages}"
    readers = (folder / "gst_jax" / "data" / "readers.html").read_text()
    assert 'id="to_model_rate"' in readers and 'id="LARGEST_ID"' not in readers
    weights = (folder / "gst_jax" / "model" / "weights.html").read_text()
    assert 'id="save"' in weights and 'id="SHIPPED_RECORD"' not in weights
    graph = (folder / "gst_jax" / "graph.html").read_text()
    assert 'id="adjacency"' in graph and 'id="EPS"' not in graph
    writer = (folder / "gst_jax" / "prediction_files.html").read_text()
    assert 'id="write_predictions"' in writer and 'id="read_predictions"' in writer


# The commands (`python -m gst_jax.<command> [<subcommand>]`) and the module of each `main`.
COMMAND_MODULES = {
    "train": "gst_jax.train", "evaluate": "gst_jax.evaluate", "sweep": "gst_jax.sweep",
    "plot": "gst_jax.plot", "navigate": "gst_jax.navigate", "predict": "gst_jax.predict.__main__",
    "simulate": "gst_jax.simulate.__main__", "conformal": "gst_jax.conformal.__main__",
    "data": "gst_jax.data.__main__", "pretrained": "gst_jax.pretrained.__main__",
    "stream": "gst_jax.stream_commands"}
COMMAND_LINE = re.compile(r"python3? -m gst_jax\.(\w+)((?:\\\n|[^`\n&|;])*)")
FLAG = re.compile(r"(?<![\w-])--[a-z][\w-]*")


@pytest.fixture(scope="module")
def flags_of() -> dict[str, set[str]]:
    """Each command's flags, from the parser its `main` builds (captured where `cli.run`
    would parse it; nothing runs), keyed "train", "plot scene", ...; a command with
    subcommands is keyed by each of them only."""
    import argparse
    import importlib

    from gst_jax import cli

    class Built(Exception):
        pass

    def built(command, parser, argv=None):
        raise Built(parser)

    def flags(parser: argparse.ArgumentParser, name: str) -> dict[str, set[str]]:
        subcommands = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if subcommands:
            return {key: value for sub, subparser in subcommands[0].choices.items()
                    for key, value in flags(subparser, f"{name} {sub}").items()}
        return {name: {o for a in parser._actions for o in a.option_strings}}

    found = {}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(cli, "run", built)
        for name, module in COMMAND_MODULES.items():
            with pytest.raises(Built) as parsed:
                importlib.import_module(module).main([])
            found.update(flags(parsed.value.args[0], name))
    return found


def _documented_command_flags(text: str) -> list[tuple[str, str, str, int]]:
    """(command, its first word, flag, line) for every flag written after `python -m
    gst_jax.<command>` on its command line (in a block or a `code span`; a backslash
    continues the line). The first word is the subcommand, if the command has any."""
    found = []
    for match in COMMAND_LINE.finditer(text):
        words = match.group(2).split()
        line = text.count("\n", 0, match.start()) + 1
        for flag in FLAG.findall(match.group(2)):
            found.append((match.group(1), words[0] if words else "", flag, line))
    return found


def test_every_documented_flag_is_a_flag_of_its_command(flags_of):
    wrong = []
    for page in DOCS:
        for command, first, flag, line in _documented_command_flags(page.read_text()):
            name = f"{command} {first}" if f"{command} {first}" in flags_of else command
            if flag not in flags_of.get(name, set()):
                wrong.append(f"{page.name}:{line}: `{name}` has no {flag}")
    assert not wrong, "\n".join(wrong)


def test_no_page_says_every_command_takes_a_flag_that_some_do_not(flags_of):
    """A sentence such as 'every command shares the flags `--scene` ...' must hold for every
    command; docs/commands.md says which takes which."""
    wrong = []
    for page in DOCS:
        prose = re.sub(r"```.*?```", "\n\n", page.read_text(), flags=re.S)
        for sentence in re.split(r"(?<=[.;])\s+|\n\s*\n", prose):
            if re.search(r"\b(every|all|any) commands?\b", sentence, re.I):
                for flag in FLAG.findall(" ".join(re.findall(r"`([^`]*)`", sentence))):
                    lacking = sorted(name for name, flags in flags_of.items()
                                     if flag not in flags)
                    if lacking:
                        wrong.append(f"{page.name}: {flag} is not a flag of {lacking}: "
                                     f"{' '.join(sentence.split())[:120]}")
    assert not wrong, "\n".join(wrong)


def test_the_table_of_shared_flags_says_which_command_takes_which(flags_of):
    rows = re.findall(r"^\| (`--.*?) \| (.*?) \|$", (ROOT / "docs" / "commands.md").read_text(),
                      re.M)
    assert len(rows) >= 10
    for flags, commands in rows:
        for flag in re.findall(r"`(--[\w-]+)`", flags):
            taking = sorted(name for name, names in flags_of.items() if flag in names)
            assert sorted(commands.split(", ")) == taking, (flag, commands)
    assert "conformal" in flags_of and "navigate evaluate" in flags_of


def test_the_readme_stays_short():
    """Detail belongs in docs/: the README is the first page a user reads."""
    assert len((ROOT / "README.md").read_text().splitlines()) <= 220


def test_the_main_jobs_printout_is_what_evaluate_printed_for_table_is_run():
    """The README's main job shows lines `evaluate` printed for Table I's run of that command
    (`format_table` of its committed record, the shipped eth_d), and the spread it quotes is
    docs/reproducing.md's measured one."""
    readme = (ROOT / "README.md").read_text()
    shown = re.search(r"```\n(eth, protocol paper.*?)```", readme, re.S).group(1).splitlines()
    record = json.loads((ROOT / "results" / "runs" / "eth-paper-d-n1-e200-seed1000.json")
                        .read_text())
    printed = format_table(record).splitlines()
    assert shown[0] == printed[0] and len(shown) >= 4
    assert all(line in printed for line in shown), shown
    assert pretrained.load_meta("eth_d")["test_metrics"]["aoe"] == record["aoe"]
    reproducing = (ROOT / "docs" / "reproducing.md").read_text()
    assert "| one core | 1.106 /" in reproducing and "| both cores | 1.188 /" in reproducing
    assert "1.106 on one core, 1.188 on two" in readme


def test_the_readme_names_every_shipped_model():
    readme = (ROOT / "README.md").read_text()
    section = re.search(r"\n## Pretrained models\n(.*?)\n## ", readme, re.S).group(1)
    assert [name for name in pretrained.available() if f"`{name}`" not in section] == []
    numbers = ("fifteen", "sixteen", "seventeen", "eighteen", "nineteen", "twenty")
    assert f"{numbers[len(pretrained.available()) - 15]} shipped models" in readme
