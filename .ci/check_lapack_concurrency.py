"""CI check: no two LAPACK custom calls of one compiled ceemx program may run concurrently.

Runs ``.ci/lapack_programs.py`` (a representative set of the library's programs; ``--quick``: the
Laplace EM programs only) in a subprocess with ``XLA_FLAGS=--xla_dump_to=DIR
--xla_dump_hlo_as_text`` and audits every optimised module XLA compiled with
``lapack_concurrency`` of ``.ci/hlo_audit.py``: two LAPACK-bearing instructions of one
computation of which neither reaches the other may run at the same time on XLA:CPU's thread pool,
and jaxlib 0.10.2's batched LAPACK kernels deadlock there (docs/known_issues.md).

Usage: ``python .ci/check_lapack_concurrency.py [--quick] [--keep DIR] [HLO_FILES_OR_DUMP_DIRS...]``
(with paths: audit those instead of running the programs). Exit status 1 on a finding.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / ".ci"))

from hlo_audit import audit_dump, lapack_concurrency  # noqa: E402


def run_programs(dump: Path, quick: bool) -> None:
    """Run .ci/lapack_programs.py with XLA's optimised HLO dumped to ``dump``."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_dump_to={dump} --xla_dump_hlo_as_text"
    env.setdefault("JAX_PLATFORMS", "cpu")
    cmd = [sys.executable, str(ROOT / ".ci" / "lapack_programs.py")] + (["--quick"] * quick)
    subprocess.run(cmd, check=True, env=env, cwd=ROOT)


def main(argv: list[str]) -> int:
    """Audit the dumps (or the given files); exit status 1 on a finding."""
    quick = "--quick" in argv
    keep = None
    paths: list[str] = []
    it = iter(a for a in argv if a != "--quick")
    for a in it:
        if a == "--keep":
            keep = next(it)
        else:
            paths.append(a)
    if paths:
        findings, modules, calls = [], 0, 0
        for p in map(Path, paths):
            if p.is_dir():
                f, m, c = audit_dump(p)
                findings += f
                modules += m
                calls += c
            else:
                findings += lapack_concurrency(p.read_text(), module=p.name)
                modules += 1
    else:
        with tempfile.TemporaryDirectory() as tmp:
            dump = Path(keep) if keep else Path(tmp)
            run_programs(dump, quick)
            findings, modules, calls = audit_dump(dump)
    for f in findings:
        print(f"concurrent LAPACK calls: {f}")
    print(
        f"LAPACK concurrency audit: {modules} compiled modules, {calls} LAPACK custom calls, "
        f"{len(findings)} concurrent pair(s)."
    )
    return 1 if findings else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
