"""One fit over several processes (:mod:`ceemx.infra.distributed`, ``fit(devices="all")``).

The slow tests start two local processes joined by ``jax.distributed`` (CPU collectives by Gloo)
on a free port, with a timeout, and compare θ and J with a one-process fit of the same data. The
default-suite tests check the set-up's argument validation, the launcher and the host reads
without starting JAX's distributed runtime (this process is a single-process run).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from ceemx.infra import distributed

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "multi_process_fit.py"
_MARKER = "DISTRIBUTED-OK"
_ENV_KEYS = (distributed.ENV_COORDINATOR, distributed.ENV_NUM_PROCESSES, distributed.ENV_PROCESS_ID)


def _clean_env() -> dict[str, str]:
    """This environment without the CEEMX_* multi-process variables (a one-process run)."""
    return {k: v for k, v in os.environ.items() if k not in _ENV_KEYS}


def _relative(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


@pytest.mark.slow  # two processes + one: 6 small fits, compiled in each process (≈ 3–6 min)
def test_two_processes_match_one_process(tmp_path):
    """examples/multi_process_fit.py as 2 processes (B split 2 + 2) and alone: θ, J to 1e-10."""
    args = ["--solver", "joint,alternate", "-B", "4", "-T", "32", "--epochs", "3"]
    one = subprocess.Popen(
        [sys.executable, str(EXAMPLE), *args, "--out", str(tmp_path / "one.json")],
        env=_clean_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        codes = distributed.launch(
            [sys.executable, str(EXAMPLE), *args, "--out", str(tmp_path / "two.json")],
            2,
            timeout=900,
            env=_clean_env(),
        )
        out, _ = one.communicate(timeout=900)
    finally:
        if one.poll() is None:
            one.kill()
            one.wait()
    assert codes == [0, 0], codes
    assert one.returncode == 0, out[-4000:]
    ref = json.loads((tmp_path / "one.json").read_text())
    two = json.loads((tmp_path / "two.json").read_text())
    assert (ref["processes"], ref["devices"]) == (1, 1)
    assert (two["processes"], two["devices"]) == (2, 2)
    worst = 0.0
    for name in ("joint", "alternate"):
        r, t = ref["fits"][name], two["fits"][name]
        worst = max(worst, _relative(t["theta"], r["theta"]), _relative(t["J"], r["J"]))
        assert len(r["J"]) == len(t["J"]) == 3, (name, r["J"], t["J"])
        assert _relative(t["theta"], r["theta"]) <= 1e-10, (name, t["theta"], r["theta"])
        assert _relative(t["J"], r["J"]) <= 1e-10, (name, t["J"], r["J"])
        assert _relative(t["states_sum"], r["states_sum"]) <= 1e-10, name
        # the fit moved: the comparison is not of two unchanged starts
        assert _relative(r["theta"], [9.0, 30.0, 2.4]) > 1e-3, (name, r["theta"])
    print(f"two processes vs one: θ and J differ by at most {worst:.1e} (relative)")


_CHILD = r"""
import sys
from ceemx.infra import distributed
distributed.initialize()
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import ceemx
from ceemx.experiments import common

pid, folder = jax.process_index(), sys.argv[1]
assert jax.process_count() == 2 and len(jax.devices()) == 2, jax.devices()
true = common.true_lorenz(1, m=2, coupling=False, process_noise=0.01, obs_noise=0.1)
p = common.lorenz_problem(0, true, B=4, T=16, sigma_w=0.01, sigma_v=0.1, coupling=False)
kw = dict(solver=ceemx.JointLM(), trainable=common.LORENZ_PARAMS, outliers="keep",
          progress=False, devices="all")


def refused(fit, *words):
    try:
        fit()
    except ValueError as e:
        assert all(w in str(e) for w in words), str(e)
    else:
        raise AssertionError(f"accepted: expected a ValueError with {words}")


# B = 3 cannot be split evenly over 2 processes' devices: refused before any compute
refused(lambda: ceemx.fit(p.init_system, p.data[np.arange(3)], p.states[:3], **kw),
        "B = 3", "2 devices", "2 processes")
# process 1 passes other data: refused by every process, naming the array and the process
y = np.array(p.data.y)
if pid == 1:
    y[2, 5, 0] += 1e-9
refused(lambda: ceemx.fit(p.init_system, ceemx.Trajectories(y), p.states, **kw),
        "`data` differs", "`y` of process 1")

# a solver that reads per-trajectory values on the host is refused, naming the supported ones
refused(lambda: ceemx.fit(p.init_system, p.data, p.states, **{**kw, "solver": ceemx.LaplaceEM()}),
        "2 processes", "ceemx.JointLM or ceemx.Alternating", "LaplaceEM")

# checkpoints: process 0 writes; 2 epochs, then resumed by both processes to 3 = 3 straight
ref = ceemx.fit(p.init_system, p.data, p.states, max_epochs=3, **kw)
first = ceemx.fit(p.init_system, p.data, p.states, max_epochs=2, checkpoint=folder, **kw)
res = ceemx.fit(p.init_system, p.data, p.states, max_epochs=3, checkpoint=folder, **kw)
assert len(first.history) == 2 and len(res.history) == 3, (first.history, res.history)
rel = lambda a, b: float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(b)))
worst = max(rel(res.theta, ref.theta), rel(res.states, ref.states),
            rel([h["J"] for h in res.history], [h["J"] for h in ref.history]))
assert worst <= 1e-10, worst
assert res.states.is_fully_addressable and res.states.shape == (4, 16, 3)
# an outlier excluded at the start (B = 4 -> 3 fitted, not a multiple of 2): fits, gathered
y = np.array(p.data.y)
y[3] += 50.0
import warnings
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    out = ceemx.fit(p.init_system, ceemx.Trajectories(y), p.states, max_epochs=1,
                    **{**kw, "outliers": "exclude"})
assert out.excluded == (3,) and np.isfinite(out.history[-1]["J"]), (out.excluded, out.history)
assert out.states.shape == (4, 16, 3) and out.states.is_fully_addressable
print(f"DISTRIBUTED-OK process {pid}, resumed fit vs straight: {worst:.1e}", flush=True)
"""


@pytest.mark.slow  # two processes, 4 JointLM fits each (≈ 2–4 min)
def test_two_processes_refuse_misuse_and_resume(tmp_path):
    """Uneven B, differing data, LaplaceEM: refused on both processes; a checkpoint resumes
    exactly; an outlier excluded at the start leaves 3 trajectories on 2 processes."""
    script = tmp_path / "child.py"
    script.write_text(_CHILD)
    log = [tmp_path / f"out{i}.txt" for i in range(2)]
    env = _clean_env()
    port = distributed.free_port()
    env[distributed.ENV_COORDINATOR] = f"127.0.0.1:{port}"
    procs = []
    for i in range(2):
        with open(log[i], "w") as f:
            procs.append(
                subprocess.Popen(
                    [sys.executable, str(script), str(tmp_path / "ckpt")],
                    env={
                        **env,
                        distributed.ENV_NUM_PROCESSES: "2",
                        distributed.ENV_PROCESS_ID: str(i),
                    },
                    stdout=f,
                    stderr=subprocess.STDOUT,
                )
            )
    try:
        for p in procs:
            p.wait(timeout=900)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    text = [f.read_text() for f in log]
    for i, p in enumerate(procs):
        assert p.returncode == 0, f"process {i}:\n{text[i][-4000:]}"
        assert f"{_MARKER} process {i}" in text[i], text[i][-2000:]
    assert any((tmp_path / "ckpt").iterdir())  # process 0 wrote it
    print(next(line for line in text[0].splitlines() if line.startswith(_MARKER)))


def test_initialize_without_variables_is_single_process(monkeypatch):
    for k in _ENV_KEYS:
        monkeypatch.delenv(k, raising=False)
    assert distributed.initialize() == 0
    assert distributed.is_main_process()


@pytest.mark.parametrize(
    ("env", "kwargs", "match"),
    [
        ({distributed.ENV_NUM_PROCESSES: "2"}, {}, "missing `coordinator_address`"),
        ({distributed.ENV_NUM_PROCESSES: "two"}, {}, "CEEMX_NUM_PROCESSES must be an integer"),
        ({}, dict(coordinator_address="h:1", num_processes=2, process_id=2), "`process_id`"),
        ({}, dict(coordinator_address="h:1", num_processes=0, process_id=0), "`num_processes`"),
        ({}, dict(coordinator_address="h", num_processes=2, process_id=0), "host:port"),
        ({}, dict(coordinator_address="h:1", num_processes=2, process_id=True), "`process_id`"),
    ],
)
def test_initialize_names_the_bad_argument(monkeypatch, env, kwargs, match):
    """Refused before JAX is touched (this process stays a single-process run)."""
    for k in _ENV_KEYS:
        monkeypatch.delenv(k, raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    with pytest.raises(ValueError, match=match):
        distributed.initialize(**kwargs)


def test_host_reads_and_same_check_in_one_process():
    x = jnp.arange(6.0).reshape(2, 3)
    np.testing.assert_array_equal(distributed.to_host(x), np.arange(6.0).reshape(2, 3))
    assert isinstance(distributed.to_host([1.0, 2.0]), np.ndarray)
    distributed.check_same("data", y=x, u=None)  # one process: nothing to compare


def test_launch_sets_the_variables_and_stops_the_others_on_failure():
    """Each process sees its id; one failing ends the rest (a collective would hang on it)."""
    code = (
        "import os, sys, time\n"
        "i = int(os.environ['CEEMX_PROCESS_ID'])\n"
        "assert os.environ['CEEMX_NUM_PROCESSES'] == '2'\n"
        "assert os.environ['CEEMX_COORDINATOR'].startswith('127.0.0.1:')\n"
        "time.sleep(60) if i == 0 else sys.exit(3)\n"
    )
    codes = distributed.launch([sys.executable, "-c", code], 2, timeout=30)
    assert codes[1] == 3 and codes[0] != 0, codes
    ok = distributed.launch([sys.executable, "-c", "pass"], 2, timeout=30)
    assert ok == [0, 0]
    with pytest.raises(ValueError, match="num_processes"):
        distributed.launch([sys.executable, "-c", "pass"], 0)
