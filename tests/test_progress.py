"""Progress: a live line on a terminal, a sparse indented line in a log."""

import io

from gst_jax import progress
from gst_jax.progress import Progress


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_live_lines_overwrite_on_a_terminal_and_appear_once_a_minute_in_a_log(monkeypatch):
    now = [0.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: now[0])
    log, terminal = io.StringIO(), _Terminal()
    in_log, on_terminal = Progress(log), Progress(terminal)
    for second in range(0, 150, 10):                    # a step every 10 s for 2.5 minutes
        now[0] = float(second)
        in_log.live(f"step at {second} s")
        on_terminal.live(f"step at {second} s")
    assert log.getvalue() == "  step at 60 s\n  step at 120 s\n"
    assert terminal.getvalue().count("\r") == 15 and "\n" not in terminal.getvalue()
    in_log.line("epoch 1 loss 0.5")
    assert log.getvalue().endswith("\nepoch 1 loss 0.5\n")
