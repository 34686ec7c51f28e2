"""Progress where stderr is no terminal: one-line logs for long work, a last line with the
outcome; a bar in a terminal or a notebook (:mod:`ceemx.infra.progress`).

The streams are captured ``io.StringIO`` objects (not a TTY); the delays are shortened so that
"long" work takes a fraction of a second.
"""

import io
import sys
import time
import types

import pytest

from ceemx.identification.fitting.epochs import outcome
from ceemx.infra import progress
from ceemx.infra.progress import Progress, interactive, task


class FakeTTY(io.StringIO):
    def isatty(self):
        return True


@pytest.fixture
def quick(monkeypatch):
    """Work counts as long after 0.05 s; heartbeats every 0.01 s; a log line every 0.1 s."""
    monkeypatch.setattr(progress, "DELAY", 0.05)
    monkeypatch.setattr(progress, "FIRST", 0.05)
    monkeypatch.setattr(progress, "EVERY", 0.1)
    monkeypatch.setattr(progress, "_TICK", 0.01)


def lines(stream) -> list[str]:
    return stream.getvalue().splitlines()


def wait_for_line(stream, n: int = 1) -> None:
    """Work that runs until the heartbeat has written ``n`` lines (5 s at most: a loaded CPU)."""
    deadline = time.perf_counter() + 5.0
    while len(lines(stream)) < n and time.perf_counter() < deadline:
        time.sleep(0.01)


def test_short_work_is_silent_unless_asked():
    quiet = io.StringIO()
    with Progress("JointLM", 5, stream=quiet) as bar:
        bar.update(1, "J=1")
    assert quiet.getvalue() == ""  # under DELAY, nobody asked: nothing
    asked = io.StringIO()
    bar = Progress("JointLM", 5, show=True, stream=asked)
    for _ in range(3):
        bar.update(1)
    bar.close(outcome([{}, {}, {"converged": True, "stop": True}], 5))
    bar.close("closing twice writes nothing")
    [line] = lines(asked)
    assert line.startswith("ceemx: JointLM: converged at 3/5 epochs (") and line.endswith(" s)")
    off = io.StringIO()
    with Progress("JointLM", 5, show=False, stream=off) as bar:
        bar.update(5)
    assert off.getvalue() == ""


def test_long_work_logs_while_it_runs(quick):
    stream = io.StringIO()
    bar = Progress("LaplaceEM (stage 2/2)", 4, stream=stream)
    bar.status("first epoch")
    wait_for_line(stream)  # past DELAY: a line that says what runs, while it runs
    first = lines(stream)
    assert first and first[0].startswith(
        "ceemx: LaplaceEM (stage 2/2): 0/4 epochs, first epoch ("
    ), first
    bar.update(2, "J=5.5")
    wait_for_line(stream, 2)
    time.sleep(0.1)  # at most one line per EVERY
    bar.close("stopped at 2/4 epochs")
    log = lines(stream)
    assert 3 <= len(log) <= 3 + 3, log
    assert any("2/4 epochs, J=5.5, running (" in line for line in log[1:-1]), log
    assert log[-1].startswith("ceemx: LaplaceEM (stage 2/2): stopped at 2/4 epochs (")


def test_task_lines(quick, monkeypatch):
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    with task("benchmark_score: 2 records of 60 steps"):
        pass
    assert stream.getvalue() == ""
    with task("diagnostics: 1 record of 40 steps"):
        wait_for_line(stream)
    log = lines(stream)
    assert log[0].startswith("ceemx: diagnostics: 1 record of 40 steps: running (")
    assert log[-1].startswith("ceemx: diagnostics: 1 record of 40 steps: done (")
    stream.truncate(0)
    stream.seek(0)
    with pytest.raises(ZeroDivisionError), task("diagnostics"):
        wait_for_line(stream)
        _ = 1 / 0
    assert lines(stream)[-1].startswith("ceemx: diagnostics: failed (")
    stream.truncate(0)
    stream.seek(0)
    with task("diagnostics", show=False):
        time.sleep(0.12)
    assert stream.getvalue() == ""


def test_where_a_bar_shows(monkeypatch):
    assert not interactive(io.StringIO())
    assert interactive(FakeTTY())
    closed = io.StringIO()
    closed.close()
    assert not interactive(closed)
    # a Jupyter kernel: stderr is no terminal, yet the bar shows (tqdm.auto picks the widget)
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    assert not interactive(sys.stderr)
    shell = type("ZMQInteractiveShell", (), {})()
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(get_ipython=lambda: shell))
    assert interactive(sys.stderr)
    assert not interactive(io.StringIO())  # another stream than stderr: no


def test_bar_ends_on_the_outcome():
    tty = FakeTTY()
    bar = Progress("JointLM", 50, stream=tty)
    assert bar.mode == "bar"
    for _ in range(8):
        bar.update(1, "J=3.25")
    bar.close("converged at 8/50 epochs")
    shown = tty.getvalue()
    assert "JointLM" in shown and "8/50" in shown
    assert shown.rstrip().endswith("converged at 8/50 epochs]"), shown[-120:]


def test_outcome_words():
    assert outcome([{"converged": True, "stop": True}] * 8, 50) == "converged at 8/50 epochs"
    assert outcome([{"converged": False, "stop": True}] * 3, 50) == "stopped at 3/50 epochs"
    assert outcome([{}] * 50, 50) == "not converged after 50/50 epochs"
    assert outcome([], 10) == "not converged after 0/10 epochs"


@pytest.mark.slow
def test_fit_scores_and_diagnostics_log_in_a_captured_stream(quick, capsys, monkeypatch):
    """A fit without a solver, its score and its diagnostics, with stderr captured (no TTY):
    every part of the fit (stage, noise round) logs its outcome under its name, the last one the
    result's; scoring and diagnostics say when they are done."""
    import jax.numpy as jnp
    import numpy as np

    import ceemx

    rng = np.random.default_rng(0)
    u = rng.uniform(0.0, 1.0, 60)
    x = np.zeros(60)
    for t in range(59):
        x[t + 1] = 0.9 * x[t] + 0.1 * u[t]
    data = ceemx.Trajectories.from_arrays(x + 0.01 * rng.standard_normal(60), u)
    start = ceemx.systems.LinearSystem(
        jnp.array([[0.5]]), jnp.array([[1.0]]), B=jnp.array([[0.3]]), D=jnp.zeros((1, 1))
    )
    capsys.readouterr()
    result = ceemx.fit(start, data, max_epochs=100, progress=True)  # every part's last line
    err = capsys.readouterr().err.splitlines()
    ends = [line for line in err if "onverged " in line and "/100 epochs, " not in line]
    assert ends and all(
        line.startswith("ceemx: JointLM (stage 1/2, noise round ") for line in ends[:-1]
    )
    assert "noise round 1): " in ends[0], err
    last_stage = result.history[-1]["stage"]  # the result's epochs: its last stage, last round
    epochs = len([h for h in result.history if h["stage"] == last_stage])
    verdict = "converged at" if result.converged else "not converged after"
    assert f"{verdict} {epochs}/100 epochs" in ends[-1], "\n".join(err)
    monkeypatch.setattr(progress, "DELAY", 0.0)  # however fast they run here (compiled or not)
    monkeypatch.setattr(progress, "_TICK", 0.001)
    ceemx.benchmark_score(result.system, data, 10)
    result.diagnostics()
    err = capsys.readouterr().err
    assert "ceemx: benchmark_score: 1 record of 60 steps: done (" in err, err
    assert "ceemx: diagnostics: 1 record of 60 steps: done (" in err, err
