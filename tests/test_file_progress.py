"""The suite names each test file as its first test starts (tests/file_progress.py): one line a
file, where `-q` and two workers write only dots."""

from __future__ import annotations

from file_progress import FileProgress


def test_each_file_is_named_once_when_its_first_test_sets_up():
    lines: list[str] = []
    clock = iter([100.0, 100.4, 165.0, 3700.0])
    progress = FileProgress(lines.append, clock=lambda: next(clock))
    progress.report("tests/test_a.py::test_one", "setup", "gw0")
    progress.report("tests/test_a.py::test_one", "call", "gw0")
    progress.report("tests/test_a.py::test_two[1]", "setup", "gw0")
    progress.report("tests/test_b.py::test_x", "call", "gw1")           # not a start
    progress.report("tests/test_b.py::test_x", "setup", "gw1")
    progress.report("tests/test_c.py::test_y", "setup")                 # one process
    assert lines == ["tests/test_a.py (gw0, at 0:00)", "tests/test_b.py (gw1, at 1:05)",
                     "tests/test_c.py (at 60:00)"]
