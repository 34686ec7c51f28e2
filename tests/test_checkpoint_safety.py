"""Checkpoints are verified before they are resumed (docs/guarantees.md, "Checkpoints").

Each test is a regression test for a way a checkpoint used to be trusted blindly: another fit's
checkpoint of the same shapes (other data, system or method options), a non-finite state, a
truncated ``latest.json``, a checkpoint of the other fit method, and an unwritable folder (which
failed only after a full epoch); and for the writes that fail part-way — a file-size limit and a
full file system, injected for real in a subprocess (tests/checkpoint_faults.py). A tiny linear
problem (n = 2, m = 1, T = 12, B = 2) keeps them fast.
"""

import dataclasses
import errno
import json
import os
import re
import stat
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from refusals import DATA, X0, decay, raises

import ceemx
from ceemx.identification.solvers import FitState
from ceemx.infra import checkpoint as ckpt
from ceemx.infra.checkpoint import CheckpointError
from ceemx.lib.results import RESULTS, select
from ceemx.systems import LinearSystem

A_TRUE = jnp.array([[0.9, 0.1], [-0.1, 0.8]])
C = jnp.array([[1.0, 0.5]])


def where_A(s: LinearSystem):
    return s.A


def system(a00=0.5, process_noise=0.1):
    A = jnp.array([[a00, 0.0], [0.0, 0.5]])
    return LinearSystem(A, C, process_noise=process_noise, obs_noise=0.1)


def dataset(seed=0):
    true = LinearSystem(A_TRUE, C, process_noise=0.1, obs_noise=0.1)
    _, data = ceemx.simulate(true, jax.random.PRNGKey(seed), jnp.ones((2, 2)), 12)
    return data


def run(folder, *, guess=None, data=None, solver=None, max_epochs=2, **kw):
    return ceemx.fit(
        system() if guess is None else guess,
        dataset() if data is None else data,
        solver=ceemx.Alternating() if solver is None else solver,
        trainable=where_A,
        max_epochs=max_epochs,
        checkpoint=str(folder),
        progress=False,
        **kw,
    )


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """A folder with the checkpoint of 2 Alternating epochs, and the result."""
    folder = tmp_path_factory.mktemp("ckpt")
    return folder, run(folder)


@pytest.fixture
def folder(written, tmp_path):
    """A private copy of the written checkpoint."""
    src, _ = written
    dst = tmp_path / "ckpt"
    dst.mkdir()
    for name in os.listdir(src):
        (dst / name).write_bytes((src / name).read_bytes())
    return dst


def test_same_fit_resumes_and_stores_fingerprint(written, folder):
    meta = json.loads((folder / "latest.json").read_text())
    assert meta["format"] == 2 and meta["fingerprint"]["method"] == "Alternating"
    assert set(meta["fingerprint"]) == set(ckpt._PARTS)
    resumed = run(folder, max_epochs=3)
    assert [h["epoch"] for h in resumed.history] == [1, 2, 3]
    assert resumed.history[:2] == json.loads(json.dumps(written[1].history))


def test_other_data_same_shapes_raises(folder):
    with pytest.raises(CheckpointError, match=r"different fit.*data \(y, u, mask; sha256\)"):
        run(folder, data=dataset(seed=1), max_epochs=3)


@pytest.mark.parametrize(
    "guess, part",
    [
        (system(process_noise=0.3), "fixed parameter values"),  # a non-trainable leaf
        (system(a00=0.6), "initial θ"),
    ],
)
def test_other_system_same_shapes_raises(folder, guess, part):
    with pytest.raises(CheckpointError, match=part) as err:
        run(folder, guess=guess, max_epochs=3)
    assert str(folder) in str(err.value) and "checkpoint_mismatch" in str(err.value)
    assert "data (y, u, mask" not in str(err.value)  # only the part that differs is named


def test_other_options_raise_and_name_the_option(folder):
    with pytest.raises(CheckpointError, match=r"method options.*rho_theta"):
        run(folder, solver=ceemx.Alternating(rho_theta=1.0), max_epochs=3)


def test_other_method_raises_naming_both(folder):
    with pytest.raises(CheckpointError, match="written by Alternating, resumed with JointLM"):
        run(folder, solver=ceemx.JointLM(), max_epochs=3)


@pytest.mark.slow
def test_other_method_old_direction(tmp_path):
    """JointLM's checkpoint resumed by Alternating (used to be a TreePathError)."""
    run(tmp_path, solver=ceemx.JointLM(), max_epochs=1)
    with pytest.raises(CheckpointError, match="written by JointLM, resumed with Alternating"):
        run(tmp_path, max_epochs=2)


def test_restart_option_starts_afresh_and_overwrites(folder):
    other = folder.parent / "fresh"
    fresh = run(other, data=dataset(seed=1), max_epochs=2)
    with pytest.warns(UserWarning, match="Starting afresh"):
        restarted = run(folder, data=dataset(seed=1), max_epochs=2, checkpoint_mismatch="restart")
    assert restarted.history[-1]["J"] == fresh.history[-1]["J"]
    meta = json.loads((folder / "latest.json").read_text())
    assert meta["fingerprint"] == json.loads((other / "latest.json").read_text())["fingerprint"]
    run(folder, data=dataset(seed=1), max_epochs=3)  # now resumes without complaint


def test_nan_theta_is_rejected(folder):
    meta = json.loads((folder / "latest.json").read_text())
    path = folder / meta["state"]
    # Load the saved state through a resume-ready template, poison θ, save it back consistently
    # (with a matching sha256, as if the run had saved it so).
    data, guess = dataset(), system()
    problem, theta = ceemx.FitProblem.create(guess, data, trainable=where_A)
    states = ceemx.Alternating().initial_states(guess, data)
    state = ceemx.Alternating().init(problem, theta, states, jax.random.PRNGKey(0))
    template = dataclasses.replace(state, cache=None)
    with open(path, "rb") as f:
        saved = eqx.tree_deserialise_leaves(f, template)
    poisoned = eqx.tree_at(lambda s: s.theta, saved, jnp.full_like(saved.theta, jnp.nan))
    ckpt.save(str(folder), poisoned, meta["history"], meta["fingerprint"])
    with pytest.raises(CheckpointError, match=r"non-finite values \(NaN or inf\) in theta"):
        run(folder, max_epochs=3)


def test_tampered_state_file_fails_its_checksum(folder):
    meta = json.loads((folder / "latest.json").read_text())
    path = folder / meta["state"]
    raw = bytearray(path.read_bytes())
    raw[-1] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(CheckpointError, match="sha256 does not match"):
        run(folder, max_epochs=3)


def test_truncated_latest_json_names_the_file(folder):
    path = folder / "latest.json"
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    with pytest.raises(CheckpointError, match=r"latest\.json.* is corrupt \(JSONDecodeError"):
        run(folder, max_epochs=3)


def test_missing_state_file_is_corrupt(folder):
    meta = json.loads((folder / "latest.json").read_text())
    os.remove(folder / meta["state"])
    with pytest.raises(CheckpointError, match="state file .* is missing"):
        run(folder, max_epochs=3)


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes to read-only folders")
def test_read_only_folder_fails_before_any_epoch(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(stat.S_IRUSR | stat.S_IXUSR)
    epochs = []
    try:
        with pytest.raises(CheckpointError, match=r"folder .*ro.* is not writable"):
            run(folder, callbacks=[lambda info: epochs.append(info.epoch)])
    finally:
        folder.chmod(stat.S_IRWXU)
    assert epochs == [] and os.listdir(folder) == []


def test_unwritable_path_fails_before_any_epoch(tmp_path):
    """Also as root: a folder below a regular file cannot be created."""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    epochs = []
    with pytest.raises(CheckpointError, match="is not writable"):
        run(blocker / "sub", callbacks=[lambda info: epochs.append(info.epoch)])
    assert epochs == []


def test_bad_mismatch_option_raises(tmp_path):
    with pytest.raises(ValueError, match="checkpoint_mismatch"):
        run(tmp_path, checkpoint_mismatch="ignore")


def test_old_format_checkpoint_resumes_with_a_warning(folder):
    path = folder / "latest.json"
    meta = json.loads(path.read_text())
    for key in ("format", "fingerprint", "state_sha256"):
        del meta[key]
    path.write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match="no fingerprint"):
        resumed = run(folder, max_epochs=3)
    assert [h["epoch"] for h in resumed.history] == [1, 2, 3]
    assert json.loads(path.read_text())["fingerprint"]["method"] == "Alternating"


def test_fingerprint_has_no_memory_addresses():
    """Functions in static fields (a log-prior here) appear without their address, so the
    fingerprint is the same in the process that resumes."""
    data, guess = dataset(), system()

    def log_prior(s):
        return -jnp.sum(s.A**2)

    problem, theta = ceemx.FitProblem.create(guess, data, trainable=where_A, log_prior=log_prior)
    fp = ckpt.fingerprint(theta, problem, theta, ceemx.Alternating())
    assert "log_prior" in fp["system_structure"]
    assert not any(" at 0x" in v for v in fp.values())


# --- write faults, for real: a file-size limit and a full file system ---------------------------

FAULTS = os.path.join(os.path.dirname(__file__), "checkpoint_faults.py")


def _mount_small_fs(path) -> str | None:
    """Mount a 64 kB tmpfs at ``path``; the reason when that is not possible here."""
    if not sys.platform.startswith("linux"):
        return "tmpfs is Linux's"
    if os.geteuid() != 0:
        return "mounting a tmpfs needs root"
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    return None if done.returncode == 0 else f"mount refused: {done.stderr.strip()}"


@pytest.fixture(scope="module")
def faults(tmp_path_factory):
    """What tests/checkpoint_faults.py saw (one subprocess: the file-size limit is its own)."""
    base = tmp_path_factory.mktemp("faults")
    disk = base / "disk"
    disk.mkdir()
    no_disk = _mount_small_fs(disk)
    try:
        done = subprocess.run(
            [sys.executable, FAULTS, str(base / "limited"), *([] if no_disk else [str(disk)])],
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
    finally:
        if no_disk is None:
            subprocess.run(["umount", str(disk)], check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1]), no_disk


KEPT = "the previous checkpoint there, if any, is kept unchanged"


@pytest.mark.parametrize(
    "scenario, files, epochs",
    [
        ("second", ["latest.json", "state-1.eqx"], 1),
        ("first", [], None),
        ("latest", ["latest.json", "state-1.eqx"], 1),
    ],
)
def test_file_size_limit_mid_write_keeps_the_last_checkpoint(faults, scenario, files, epochs):
    """A write past ``ulimit -f`` writes what fits; the state file's read "800 requested and
    340 written (errno None)" (NumPy's writer), at the first save as at a later one."""
    seen = faults[0][scenario]
    assert "File too large (EFBIG, errno 27" in seen["error"] and KEPT in seen["error"]
    assert seen["files"] == files and seen["epochs"] == epochs  # no temporaries; resumable


def test_file_size_limit_at_the_probe_leaves_nothing(faults):
    seen = faults[0]["probe"]
    assert "is not writable (File too large)" in seen["error"] and seen["files"] == []


def test_full_small_file_system_keeps_the_last_checkpoint(faults):
    """A 64 kB tmpfs with 4 kB left under a 24 kB state file: the write stops short; it read
    "3000 requested and 477 written (errno None)". Space again: it resumes and saves."""
    results, no_disk = faults
    if no_disk:
        pytest.skip(no_disk)
    seen = results["disk"]
    assert "No space left on device (ENOSPC, errno 28)" in seen["error"] and KEPT in seen["error"]
    assert seen["files"] == ["latest.json", "state-1.eqx"]
    assert seen["epochs"] == 1 and seen["epochs_after"] == 2


def small_state(**replace):
    state = FitState(
        theta=jnp.zeros(3),
        states=jnp.zeros((2, 4, 1)),
        J=jnp.zeros(2),
        weights=jnp.ones(2),
        status=select(jnp.zeros(2, bool), RESULTS.nonfinite, RESULTS.successful),
        solver_state=(jnp.asarray(1e-3), jnp.zeros(2), jnp.zeros((2, 4, 1))),
    )
    return dataclasses.replace(state, **replace)


FP = {"method": "a test's fit state"}


def test_a_write_short_again_on_its_retry_is_no_space(tmp_path, monkeypatch):
    """The rule for short writes, which no file system here produces twice in a row: a short
    write is retried once (a retry that writes the rest saves), a second short one is ENOSPC."""
    folder = str(tmp_path)
    real, calls = os.write, []

    def short_once(fd, data):  # the first write takes half, the retry the rest
        calls.append(len(data))
        return real(fd, bytes(data[: len(data) // 2]) if len(calls) == 1 else data)

    monkeypatch.setattr(os, "write", short_once)
    ckpt.save(folder, small_state(), [{"epoch": 1}], FP)
    monkeypatch.setattr(os, "write", lambda fd, data: real(fd, bytes(data[: len(data) // 2])))
    with pytest.raises(CheckpointError, match=r"a write stopped short: \d+ of \d+ bytes.*ENOSPC"):
        ckpt.save(folder, small_state(), [{"epoch": 1}, {"epoch": 2}], FP)
    monkeypatch.undo()
    assert sorted(os.listdir(folder)) == ["latest.json", "state-1.eqx"]
    assert ckpt.load(folder, small_state(), fingerprint=FP)[1] == [{"epoch": 1}]


@pytest.mark.parametrize("call", ["fsync", "close"])
def test_failure_at_fsync_or_close_keeps_the_last_checkpoint(tmp_path, monkeypatch, call):
    """An I/O error surfacing only at fsync or close (delayed allocation, network file systems;
    not producible on this machine's file systems) is named like a failed write."""
    folder = str(tmp_path)
    ckpt.save(folder, small_state(), [{"epoch": 1}], FP)
    real = getattr(os, call)

    def failing(fd):
        real(fd)
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(os, call, failing)
    with pytest.raises(CheckpointError, match=r"Input/output error \(EIO, errno 5\); " + KEPT):
        ckpt.save(folder, small_state(), [{"epoch": 1}, {"epoch": 2}], FP)
    monkeypatch.undo()
    assert sorted(os.listdir(folder)) == ["latest.json", "state-1.eqx"]


@pytest.mark.parametrize(
    "leaf, name",
    [(1, "solver_state[1]"), (2, "solver_state[2]")],
    ids=["log-evidence", "smoother-start"],
)
def test_nan_in_a_per_trajectory_solver_leaf_is_not_resumed(tmp_path, leaf, name):
    """Laplace EM keeps (learner state, (B,) log-evidence, (B, T, n) smoother start): only its
    scalars were checked, so a NaN log-evidence of a trajectory taking part was resumed."""
    solver_state = list(small_state().solver_state)
    solver_state[leaf] = solver_state[leaf].at[0].set(jnp.nan)
    ckpt.save(str(tmp_path), small_state(solver_state=tuple(solver_state)), [{"epoch": 1}], FP)
    with pytest.raises(CheckpointError, match=re.escape(f"(NaN or inf) in {name}")):
        ckpt.load(str(tmp_path), small_state(), fingerprint=FP)


def test_nan_of_an_excluded_trajectory_is_resumed(tmp_path):
    """A failed trajectory (weight 0) keeps NaN in its per-trajectory entries; no epoch reads
    them, so the checkpoint resumes."""
    nan_first = (jnp.asarray(1e-3), jnp.asarray([jnp.nan, 0.0]), jnp.zeros((2, 4, 1)))
    state = small_state(weights=jnp.asarray([0.0, 1.0]), solver_state=nan_first)
    ckpt.save(str(tmp_path), state, [{"epoch": 1}], FP)
    tree, _ = ckpt.load(str(tmp_path), small_state(), fingerprint=FP)
    assert np.isnan(np.asarray(tree.solver_state[1])[0])


# --- checkpoints on full disks; what a resume trusts --------------------------------------------


def fit_state(weights=(1.0, 1.0), lam=1e-3):
    return FitState(
        theta=jnp.zeros(3),
        states=jnp.zeros((2, 4, 1)),
        J=jnp.zeros(2),
        weights=jnp.asarray(weights),
        status=select(jnp.zeros(2, bool), RESULTS.nonfinite, RESULTS.successful),
        solver_state=jnp.asarray(lam),
    )


# A fingerprint for the checkpoints written here (one without would be resumed with a warning,
# as from an older ceemx: test_old_format_checkpoint_resumes_with_a_warning).
FINGERPRINT = {"method": "a test's fit state"}


@pytest.mark.parametrize(
    "state, what",
    [
        (fit_state(weights=(np.nan, 1.0)), "weights"),
        (fit_state(lam=np.nan), "solver_state"),
    ],
    ids=["nan-weights", "nan-damping"],
)
def test_resume_refuses_nonfinite_weights_and_solver_scalars(tmp_path, state, what):
    """NaN weights used to resume (J then read 0), as did a NaN damping λ."""
    ckpt.save(str(tmp_path), state, [{"epoch": 1}], FINGERPRINT)
    with raises(ckpt.CheckpointError, f"non-finite values (NaN or inf) in {what}"):
        ckpt.load(str(tmp_path), fit_state(), fingerprint=FINGERPRINT)


def test_resume_refuses_a_history_that_does_not_match_its_epoch(tmp_path):
    """An emptied history resumed as converged=True with the wrong epoch count."""
    ckpt.save(str(tmp_path), fit_state(), [{"epoch": 1}, {"epoch": 2}], FINGERPRINT)
    path = tmp_path / "latest.json"
    meta = json.loads(path.read_text())
    path.write_text(json.dumps({**meta, "history": []}))
    with raises(ckpt.CheckpointError, "epoch 2 does not match the 0 epochs of its history"):
        ckpt.load(str(tmp_path), fit_state())


# --- one writer per checkpoint folder -----------------------------------------------------------

_HOLDER = """
import sys
from ceemx.infra.folder_lock import folder_lock
with folder_lock(sys.argv[1], RuntimeError):
    print("held", flush=True)
    sys.stdin.read()
"""


def hold_in_another_process(folder):
    """A process holding ``folder``'s lock until its stdin closes (imports nothing heavy)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(folder)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stdout.readline() == "held\n"
    return proc


def test_a_second_writer_is_refused_naming_the_first(tmp_path):
    """Two fits on one folder used to remove each other's temporaries and crash
    (FileNotFoundError … .tmp-… -> state-8.eqx); the second is now refused at once."""
    proc = hold_in_another_process(tmp_path)
    try:
        with raises(ckpt.CheckpointError, f"is in use by another fit (pid {proc.pid} on host"):
            with ckpt.lock(str(tmp_path)):
                pass
    finally:
        proc.communicate("")
    with ckpt.lock(str(tmp_path)):  # free once the first has finished
        assert os.listdir(tmp_path) == [".lock"]
    assert os.listdir(tmp_path) == []  # removed on release


def test_the_lock_of_a_killed_writer_is_taken_over(tmp_path):
    proc = hold_in_another_process(tmp_path)
    proc.kill()
    proc.communicate()  # waits, and closes its pipes
    assert os.listdir(tmp_path) == [".lock"]  # left behind, but no longer held
    with ckpt.lock(str(tmp_path)):
        assert f"pid {os.getpid()} on host" in (tmp_path / ".lock").read_text()


def test_fit_on_a_folder_in_use_is_refused_before_compute(no_compute, tmp_path):
    """Also within one process: the lock is per open file, and held for the fit's lifetime."""
    with ckpt.lock(str(tmp_path)):
        with raises(ckpt.CheckpointError, "is in use by another fit"):
            ceemx.fit(decay(), DATA, X0, checkpoint=str(tmp_path), solver=ceemx.Alternating())
    assert os.listdir(tmp_path) == []


def _strict_json(text: str):
    """JSON as the standard defines it: ``NaN``, ``Infinity`` and ``-Infinity`` refused."""

    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


def test_nonfinite_history_is_valid_json_and_reads_back(tmp_path):
    # a failed trajectory's J is −inf or NaN in the history: latest.json held -Infinity and NaN,
    # which strict JSON readers refuse; now tagged, and read back as the same floats
    history = [
        {"epoch": 1, "J": -np.inf, "J_b": [1.5, np.nan], "rate": np.float32("inf"), "note": None},
        {"epoch": 2, "J": np.float64("nan"), "J_b": np.array([-np.inf, 2.0]), "ok": True},
    ]
    tree = {"a": jnp.arange(2.0)}
    ckpt.save(str(tmp_path), tree, history, {"method": "x"})
    meta = _strict_json((tmp_path / "latest.json").read_text())
    assert meta["history"][0]["J"] == {"nonfinite": "-inf"}
    _, back = ckpt.load(str(tmp_path), tree, None)
    assert back[0]["J"] == -np.inf and back[0]["rate"] == np.inf and back[0]["note"] is None
    assert back[0]["J_b"][0] == 1.5 and np.isnan(back[0]["J_b"][1])
    assert np.isnan(back[1]["J"]) and back[1]["J_b"] == [-np.inf, 2.0] and back[1]["ok"] is True
