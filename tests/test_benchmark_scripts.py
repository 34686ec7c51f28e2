"""The benchmark scripts' ``--smoke`` modes run, so they cannot rot.

A peer or the reference implementation whose environment is absent is skipped by the script
itself with a message (the reference: ``benchmarks/reference/setup.sh``).
"""

import ast
import importlib
import json
import pathlib
import subprocess
import sys
import types

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _run_script(
    name: str, tmp_path, *extra, python: str = sys.executable
) -> subprocess.CompletedProcess:
    out = tmp_path / f"{name}.json"
    return subprocess.run(
        [
            python,
            str(ROOT / "benchmarks" / f"{name}.py"),
            "--smoke",
            "--out",
            str(out),
            *extra,
        ],
        capture_output=True,
        text=True,
        timeout=900,
    )


@pytest.mark.slow  # two fresh processes compile two fit solvers (≈ 30–60 s)
def test_compare_reference_smoke(tmp_path):
    proc = _run_script("compare_reference", tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((tmp_path / "compare_reference.json").read_text())
    summary = res["summary"]
    for method in ("joint", "alternate"):
        assert summary[method]["first_fit_s_median"] > 0
        assert summary[method]["max_rel_error"] < 0.2
    if (ROOT / "benchmarks" / "reference" / ".venv" / "bin" / "python").exists():
        assert summary["reference"]["fit_s_median"] > 0
    else:
        assert "reference environment absent" in proc.stdout


#: The peers' environment (``benchmarks/peers/setup.sh``: dynamax, cuthbert, jax-sysid beside an
#: editable ceemx); without it the peer scripts run on this Python and skip the peers.
PEERS_PYTHON = ROOT / "benchmarks" / "peers" / ".venv" / "bin" / "python"


def _peers_python() -> str:
    return str(PEERS_PYTHON) if PEERS_PYTHON.exists() else sys.executable


@pytest.mark.slow  # compiles the smoother and two EKS (≈ 20 s)
def test_compare_peers_smoke(tmp_path):
    proc = _run_script("compare_peers", tmp_path, python=_peers_python())
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((tmp_path / "compare_peers.json").read_text())
    assert res["ceemx"]["steady_s_median"] > 0 and res["ceemx"]["rmse"] < 1.0
    for peer in ("dynamax", "cuthbert"):
        if peer in res:
            assert res[peer]["steady_s_median"] > 0 and res[peer]["rmse"] < 1.0
        else:
            assert f"{peer} absent" in proc.stdout and peer in res["absent"]
    if "dynamax" in res and "cuthbert" in res:  # the same extended Kalman smoother
        assert res["cuthbert"]["max_abs_diff_to_dynamax"] < 1e-5


@pytest.mark.slow  # one identification per method, compiles ceemx's fit and the EKF L-BFGS (≈ 60 s)
def test_compare_peers_sysid_smoke(tmp_path):
    proc = _run_script("compare_peers_sysid", tmp_path, python=_peers_python())
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((tmp_path / "compare_peers_sysid.json").read_text())
    ours = res["summary"]["ceemx"]
    assert ours["fits"] == 1 and ours["steady_s_median"] > 0
    assert ours["max_rel_error_max"] < 0.05
    for peer in ("ekf_lbfgs", "jax_sysid"):
        if peer in res["summary"]:  # a peer's accuracy is a finding, not a requirement
            assert res["summary"][peer]["fits"] == 1
            assert res["summary"][peer]["first_call_s"] > 0
        else:
            assert f"{peer} absent" in proc.stdout and peer in res["absent"]


@pytest.mark.slow  # one fresh process per device count (≈ 40–60 s)
def test_multi_device_smoke(tmp_path):
    proc = _run_script("multi_device", tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((tmp_path / "multi_device.json").read_text())
    assert res


@pytest.mark.slow  # a fresh process compiles two fit solvers on K = 6 (≈ 30 s)
def test_compare_reference_figure3_smoke(tmp_path):
    proc = _run_script("compare_reference_figure3", tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((tmp_path / "compare_reference_figure3.json").read_text())
    for method in ("alternate", "joint"):
        eps = res["summary"][method]["eps_per_epoch"]
        assert len(eps) == 2 and all(e > 0 for e in eps)
    joint = res["summary"]["joint"]["eps_per_epoch"]
    assert joint[-1] < joint[0]


@pytest.mark.slow  # as above, with a 20 s budget per implementation
def test_compare_reference_figure3_time_to_eps_smoke(tmp_path):
    proc = _run_script("compare_reference_figure3", tmp_path, "--time-to-eps")
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((tmp_path / "compare_reference_figure3.json").read_text())
    joint = res["summary"]["joint"]
    assert joint["time_to_eps_10_s"][0] is not None  # the joint method gets below ε = 10
    assert min(joint["eps_per_epoch"]) == joint["best_eps"][0]
    for method in ("alternate", "joint"):
        assert res["summary"][method]["total_s"][0] > 0


@pytest.mark.slow  # compiles Particle EM and CE-EM on a tiny problem; the reference, if present
def test_particle_em_smoke(tmp_path):
    proc = _run_script("particle_em", tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads((tmp_path / "particle_em.json").read_text())
    summary = res["summary"]
    assert summary["ceemx_particle_em"]["s_per_epoch"] > 0
    assert summary["ceemx_ce_em"]["s_per_epoch"] > 0
    assert len(res["loads"]) == 1 and len(res["runs"]) == 1
    if (ROOT / "benchmarks" / "reference" / ".venv" / "bin" / "python").exists():
        ref = summary["reference_particle_em"]
        assert ref["s_per_epoch"] > 0 and len(ref["theta_last"]) == 1
        assert summary["speedup_particle_em_same_run"] > 0
    else:
        assert "reference environment absent" in proc.stdout


def test_speed_table_renders_every_row_from_the_committed_results():
    """``benchmarks/speed_table.py --table-only`` reads each row script's JSON as committed: a
    script whose output format drifts from what the table reads fails here (no JAX, < 1 s)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import speed_table
    finally:
        sys.path.pop(0)
    out = ROOT / "benchmarks" / "results"
    text = speed_table.table(out, json.loads((out / "speed_table.json").read_text())["rows"])
    rows = [line for line in text.splitlines() if line.startswith("| ") and "---" not in line]
    assert len(rows) == 1 + 13  # the header and every measure (sub-rows included)
    for needle in ("Figure-3", "warm cache", "ceemx demo", "K = 100", "Laplace EM",
                   "two processes", "parallel-in-time", "T = 10⁴…10⁵"):  # fmt: skip
        assert any(needle in r for r in rows), needle
    assert all(r.count("|") == 7 for r in rows)  # six cells each


# --- every ceemx name a script uses exists (no script runs) ------------------------------------


def _scopes(body):
    """(statements of one scope, the functions defined in it) — a function is its own scope."""
    nodes, functions, stack = [], [], list(body)
    while stack:
        node = stack.pop()
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            functions.append(node)
            continue
        nodes.append(node)
        stack.extend(ast.iter_child_nodes(node))
    return nodes, functions


def _resolve(module, names: list[str]):
    """The object at ``module.names[0].names[1]...`` (submodules imported); ``None``: missing.

    Stops at the first object that is not a module (a class's attributes are not checked).
    """
    obj = module
    for name in names:
        if not isinstance(obj, types.ModuleType):
            return obj
        if hasattr(obj, name):
            obj = getattr(obj, name)
            continue
        try:
            obj = importlib.import_module(f"{obj.__name__}.{name}")
        except ImportError:
            return None
    return obj


def _missing_in_scope(body, arguments, aliases: dict, problems: list[str]) -> None:
    """Check one scope's ceemx imports and the attributes read or set on imported modules."""
    nodes, functions = _scopes(body)
    aliases = {k: v for k, v in aliases.items() if k not in arguments}
    for node in nodes:  # a name bound here to something else hides a module of an outer scope
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            aliases.pop(node.id, None)
    for node in nodes:
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] != "ceemx":
                    continue
                module = _resolve(importlib.import_module("ceemx"), a.name.split(".")[1:])
                if module is None:
                    problems.append(f"line {node.lineno}: import {a.name}")
                else:
                    aliases[a.asname or "ceemx"] = module if a.asname else sys.modules["ceemx"]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "ceemx":
            module = _resolve(importlib.import_module("ceemx"), node.module.split(".")[1:])
            for a in node.names:
                obj = None if module is None else _resolve(module, [a.name])
                if obj is None:
                    problems.append(f"line {node.lineno}: from {node.module} import {a.name}")
                elif isinstance(obj, types.ModuleType):
                    aliases[a.asname or a.name] = obj
    for node in nodes:
        chain, base = [], node
        while isinstance(base, ast.Attribute):
            chain.append(base.attr)
            base = base.value
        if chain and isinstance(base, ast.Name) and base.id in aliases:
            if _resolve(aliases[base.id], chain[::-1]) is None:
                problems.append(f"line {node.lineno}: {base.id}.{'.'.join(chain[::-1])}")
    for fn in functions:
        args = {a.arg for a in ast.walk(fn.args) if isinstance(a, ast.arg)}
        body = fn.body if isinstance(fn.body, list) else [fn.body]
        _missing_in_scope(body, args, aliases, problems)


@pytest.mark.parametrize(
    "script", sorted(p.name for p in (ROOT / "benchmarks").glob("*.py")), ids=lambda s: s[:-3]
)
def test_script_uses_only_ceemx_names_that_exist(script):
    """Every ``ceemx`` module and name a benchmark script imports, and every attribute it reads or
    patches on an imported ceemx module, exists (``ast`` + ``importlib``; no script runs): a name
    renamed or moved in the library fails here, not in the script's next run."""
    problems: list[str] = []
    tree = ast.parse((ROOT / "benchmarks" / script).read_text())
    _missing_in_scope(tree.body, set(), {}, problems)
    assert not problems, problems
