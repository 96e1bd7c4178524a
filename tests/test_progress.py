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


def test_the_eta_leaves_out_the_first_step_and_compiling(monkeypatch):
    now = [0.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: now[0])
    clock = progress.StepClock()
    now[0] = 150.0                                      # step 1: 140 s compiling, 10 s warm-up
    assert clock.eta(1, 99, compile_seconds=140.0) == "--"
    now[0] = 170.0                                      # steps 2-11: 2 s each
    assert clock.eta(11, 89, compile_seconds=140.0) == "0:02:58"
    now[0] = 200.0                                      # steps 12-16: 2 s each, 20 s compiling
    assert clock.eta(16, 84, compile_seconds=160.0) == "0:02:48"
