"""Which test file the suite is in: the suite runs quietly (`-q`, two workers, pyproject.toml),
which writes one dot a test and no file name, so a newcomer watched 40 minutes of dots. This
writes one line as each file's first test starts: its path, the worker that runs it and the
time into the suite (`tests/test_train.py (gw0, at 0:00)`), and nothing more; conftest.py
hooks it into the process that writes to the terminal."""

from __future__ import annotations

import time
from typing import Callable


class FileProgress:
    """`report(nodeid, when, worker)` for every test report; writes through `write_line` the
    first time a file's test sets up."""

    def __init__(self, write_line: Callable[[str], None],
                 clock: Callable[[], float] = time.monotonic):
        self.write_line, self.clock = write_line, clock
        self.started = clock()
        self.seen: set[str] = set()

    def report(self, nodeid: str, when: str, worker: str | None = None) -> None:
        path = nodeid.split("::")[0]
        if when != "setup" or path in self.seen:
            return
        self.seen.add(path)
        seconds = int(self.clock() - self.started)
        by = f"{worker}, " if worker else ""
        self.write_line(f"{path} ({by}at {seconds // 60}:{seconds % 60:02d})")
