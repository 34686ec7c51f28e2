"""The ``ceemx`` command under interrupts and bad arguments, and atomic result files.

- Usage errors (``--seeds 0``, an ``--out`` that cannot be written) exit 2 with one line, before
  any compute and without importing JAX (``ceemx --help`` too: parsing is import-light).
- Result files are replaced atomically; under :func:`ceemx.evaluation.report.deferred_writes`
  nothing is written until the commit, ``results.json`` last.
- SIGINT: exit status 130, exactly one line on stderr, no ``results.json``; SIGTERM the same with
  status 143; the ``--out`` folder the run created is removed when nothing was written to it.
"""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from ceemx import cli
from ceemx.evaluation import report
from ceemx.experiments import common

# ----------------------------------------------------------------------------------------------
# Usage errors
# ----------------------------------------------------------------------------------------------


def usage_error(capsys, argv) -> str:
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and "error" in lines[0], err
    return lines[0]


@pytest.mark.parametrize("seeds", ["0", "-1", "-3", ",", "x", "1,x"])
@pytest.mark.parametrize("name", ["table1", "figure3"])
def test_bad_seeds_are_usage_errors(capsys, tmp_path, name, seeds):
    line = usage_error(capsys, ["experiment", name, f"--seeds={seeds}", "--out", str(tmp_path)])
    assert "--seeds" in line
    assert not list(tmp_path.iterdir())


def test_seed_counts_below_one_raise():
    for text in ("0", "-2", ",", " , "):
        with pytest.raises(ValueError):
            common.parse_seeds(text)
    with pytest.raises(ValueError):
        common.seed_list(0, first=42, default=4)
    with pytest.raises(ValueError):
        common.seed_list([], first=42, default=4)
    assert common.parse_seeds("1") == 1


def test_unwritable_out_is_a_usage_error(capsys, tmp_path):
    a_file = tmp_path / "file"
    a_file.write_text("x")
    for out in (a_file, a_file / "sub"):  # an existing file; a folder under a file
        line = usage_error(capsys, ["experiment", "table1", "--smoke", "--out", str(out)])
        assert "--out" in line and str(out) in line
        line = usage_error(capsys, ["demo", "--smoke", "--out", str(out)])
        assert "--out" in line
    assert a_file.read_text() == "x"


def imported(stderr: str) -> tuple[set[str], list[str]]:
    """The modules a ``python -X importtime`` process imported, and its other lines of stderr."""
    modules, other = set(), []
    for line in stderr.splitlines():
        if line.startswith("import time:"):
            modules.add(line.rsplit("|", 1)[-1].strip())
        else:
            other.append(line)
    return modules, other


def test_usage_error_subprocess_one_line(tmp_path):
    """The installed path (``python -m ceemx``): status 2, one line on stderr, nothing written,
    and JAX never imported (a usage error answers at once; ``-X importtime`` lists the imports)."""
    out = tmp_path / "out"
    args = ["experiment", "figure3", "--seeds", "0", "--out", str(out)]
    r = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "ceemx", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2
    modules, lines = imported(r.stderr)
    assert len(lines) == 1, lines
    assert "ceemx.cli" in modules
    assert not modules & {"jax", "jaxlib", "equinox"}, sorted(modules)
    assert not out.exists()


def test_output_dir_probes_writability(tmp_path):
    assert report.output_dir(tmp_path / "a" / "b", "unused") == tmp_path / "a" / "b"
    assert not list((tmp_path / "a" / "b").iterdir())  # the probe file is gone
    (tmp_path / "f").write_text("")
    with pytest.raises(OSError):
        report.output_dir(tmp_path / "f", "unused")


# ----------------------------------------------------------------------------------------------
# Atomic writes
# ----------------------------------------------------------------------------------------------


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "results.json"
    report.save_json(path, {"a": 1})

    def fail(fd):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(OSError, match="disk full"):
        report.save_json(path, {"a": 2, "b": list(range(1000))})
    with pytest.raises(OSError, match="disk full"):
        report.save_text(tmp_path / "table.md", "| a |\n")
    assert json.loads(path.read_text()) == {"a": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]  # no temp files left


def test_files_have_an_ordinary_mode(tmp_path):
    umask = os.umask(0o022)
    os.umask(umask)
    path = report.save_text(tmp_path / "table.md", "x")
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_deferred_writes(tmp_path):
    plt = report.plt()
    with report.deferred_writes() as held:
        report.save_json(tmp_path / "results.json", {"a": 1})
        report.save_text(tmp_path / "table.md", "t")
        fig, _ = plt.subplots()
        report.save_figure(fig, tmp_path / "fig.png")
        assert not list(tmp_path.iterdir())
    assert not list(tmp_path.iterdir())  # leaving the block writes nothing
    order = held.commit()
    assert order[-1].name == "results.json"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png", "results.json", "table.md"]
    assert (tmp_path / "fig.png").read_bytes()[:4] == b"\x89PNG"
    with report.deferred_writes():
        report.save_json(tmp_path / "results.json", {"a": 2})
    assert json.loads((tmp_path / "results.json").read_text()) == {"a": 1}  # not committed


# ----------------------------------------------------------------------------------------------
# SIGINT
# ----------------------------------------------------------------------------------------------


def interrupt(tmp_path, delay: float | str | None, signum=signal.SIGINT):
    """Run ``python -m ceemx experiment table1 --smoke``, send ``signum`` after ``delay`` s — or,
    with ``delay=None``, as soon as the first fit's line is printed (mid-fitting, any machine
    speed); with ``delay="out"``, as soon as the ``--out`` folder exists (nothing imported yet)."""
    out = tmp_path / f"out-{delay}" / "run"
    env = dict(os.environ, MPLBACKEND="Agg", CEEMX_COMPILATION_CACHE="0")
    env["PYTHONUNBUFFERED"] = "1"  # the first fit's line arrives as it is printed
    proc = subprocess.Popen(
        [sys.executable, "-m", "ceemx", "experiment", "table1", "--smoke", "--out", str(out)],
        stdout=subprocess.PIPE if delay is None else subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=env,
        cwd=tmp_path,
    )
    if delay is None:
        assert proc.stdout is not None
        first = proc.stdout.readline().decode()
        assert first.startswith("[likelihood"), first
    elif delay == "out":
        while not out.exists() and proc.poll() is None:
            time.sleep(0.005)
    else:
        time.sleep(delay)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    err = err.decode()
    assert proc.returncode == 128 + signum, (proc.returncode, err)
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].strip(), err
    # nothing written, and the folders the run made for --out (out-…/run) removed again
    assert not out.parent.exists(), list(out.parent.rglob("*"))
    return lines[0]


@pytest.mark.slow
def test_sigterm_like_sigint(tmp_path):
    """SIGTERM ends the run as SIGINT does: one line, status 143, no half-written ``--out``
    folder (it used to kill the run silently, leaving an empty one) — here sent once ``--out``
    exists (≈ 0.5 s)."""
    assert interrupt(tmp_path, "out", signal.SIGTERM) == "ceemx: terminated"


@pytest.mark.slow
@pytest.mark.parametrize("delay", [3.0, None])
def test_sigterm_while_compiling_and_fitting(tmp_path, delay):
    assert interrupt(tmp_path, delay, signal.SIGTERM) == "ceemx: terminated"


def test_sigint_one_line_130(tmp_path):
    """One quick case: SIGINT as soon as ``--out`` exists (≈ 0.5 s; the slow cases cover SIGINT
    while compiling and mid-fit)."""
    interrupt(tmp_path, "out")


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.5, 3.0, None])
def test_sigint_at_several_times(tmp_path, delay):
    """Import of the package, compilation, fitting (right after the first fit's line)."""
    interrupt(tmp_path, delay)
