"""Find LAPACK custom calls that may run concurrently inside one compiled XLA:CPU program.

jaxlib 0.10.2's CPU LAPACK kernels (``lapack_*_ffi``: eigh/syevd, Cholesky/potrf, LU/getrf,
triangular solves/trsm, QR/geqrf, SVD/gesdd, …) split a batch over XLA's intra-op thread pool and
block the calling thread until the pieces are done. XLA:CPU's thunk executor runs independent
thunks concurrently *on that same pool*; when as many batched LAPACK calls as the pool has
workers start at once (two on a 2-core machine), each occupies a worker while waiting for work
that only a free worker could run: a deadlock, intermittent per call (docs/known_issues.md).

The library therefore never leaves two LAPACK calls of one program independent of each other.
:func:`lapack_concurrency` checks that on optimised HLO text (``jax.jit(f).lower(...).compile()
.as_text()``, or the ``*after_optimizations.txt`` files of ``XLA_FLAGS=--xla_dump_to=DIR
--xla_dump_hlo_as_text``): per computation it builds the dataflow graph, marks an instruction
*LAPACK-bearing* when it is a batched LAPACK custom call (batch count ≥ 2: jaxlib runs a single
matrix inline, it never fans out) or calls (``while``, ``conditional``, ``call``,
``fusion``, …) a computation that holds one, and reports every pair of LAPACK-bearing
instructions in the same computation of which neither reaches the other.

The thunk executor orders thunks by the buffers they read and write, not by the HLO graph, so
the graph here follows buffers: element *i* of a ``tuple`` or ``opt-barrier`` read through
``get-tuple-element`` depends only on operand *i* (a barrier aliases its operands and emits no
thunk — it does not sequence anything at run time), and control predecessors are no edges. A
reported pair can still be ordered by buffer reuse, so the check may over-report, never
under-report (short of a program the executor runs sequentially anyway, which it decides by
buffer sizes at run time).

Host-side text processing (:func:`compiled_hlo` only calls the ``lower``/``compile`` methods of
the function it is given); imports nothing of JAX. CI tooling, not part of the library:
``.ci/check_lapack_concurrency.py`` runs it on every program of ``.ci/lapack_programs.py``, and
``tests/test_lapack_safety.py`` imports it from this folder.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterable, Iterator
from pathlib import Path

__all__ = ["ConcurrentLapack", "audit_dump", "compiled_hlo", "lapack_calls", "lapack_concurrency"]

#: custom-call targets that are jaxlib's CPU LAPACK kernels
LAPACK_TARGET = re.compile(r"^lapack_")

_HEADER = re.compile(r"^(?:ENTRY\s+)?%?(?P<name>[^\s(]+)\s*\(.*\{\s*$")
_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?(?P<name>[^\s=]+)\s*=\s*(?P<rest>.*)$")
_CALLED = re.compile(
    r"\b(?:calls|to_apply|body|condition|true_computation|false_computation)=%?([\w.\-]+)"
)
_CALLED_SET = re.compile(r"\b(?:calls|branch_computations|called_computations)=\{([^}]*)\}")
_TARGET = re.compile(r'custom_call_target="([^"]+)"')
_INDEX = re.compile(r"\bindex=(\d+)")
_OP_NAME = re.compile(r'op_name="([^"]*)"')
_FRAME = re.compile(r"\bstack_frame_id=(\d+)")
_TABLES = ("FileNames", "FunctionNames", "FileLocations", "StackFrames")


@dataclasses.dataclass(frozen=True)
class _Instruction:
    name: str
    shape: str
    opcode: str
    operands: tuple[str, ...]
    called: tuple[str, ...]
    target: str | None
    index: int | None
    op_name: str
    frame: int | None


@dataclasses.dataclass(frozen=True)
class ConcurrentLapack:
    """Two LAPACK-bearing instructions of one computation, neither reaching the other.

    Attributes:
        module: the HLO module (``jit_<function>``; a dump's file stem).
        computation: the computation holding both.
        first, second: the instructions (a custom call, or a while/conditional/call around one).
        first_targets, second_targets: the LAPACK targets each runs, with their batch counts
            (its own, or those in the computations it calls).
        first_op, second_op: where each is in the program: the innermost source line JAX
            recorded (``file:line (function)``), else its ``op_name`` metadata.
    """

    module: str
    computation: str
    first: str
    second: str
    first_targets: tuple[str, ...]
    second_targets: tuple[str, ...]
    first_op: str
    second_op: str

    def __str__(self) -> str:
        return (
            f"{self.module} / {self.computation}: {self.first} "
            f"[{', '.join(self.first_targets)}] ({self.first_op}) ∥ {self.second} "
            f"[{', '.join(self.second_targets)}] ({self.second_op})"
        )


def _balanced(text: str, start: int) -> int:
    """Index just past the bracket group opening at ``text[start]`` (``(``, ``{`` or ``[``)."""
    depth = 0
    for i in range(start, len(text)):
        c = text[i]
        if c in "({[":
            depth += 1
        elif c in ")}]":
            depth -= 1
            if depth == 0:
                return i + 1
    return len(text)


def _split_top(text: str) -> list[str]:
    """``text`` split at the commas outside brackets."""
    parts, depth, last = [], 0, 0
    for i, c in enumerate(text):
        if c in "({[":
            depth += 1
        elif c in ")}]":
            depth -= 1
        elif c == "," and depth == 0:
            parts.append(text[last:i])
            last = i + 1
    parts.append(text[last:])
    return [p.strip() for p in parts if p.strip()]


def _parse_instruction(name: str, rest: str) -> _Instruction | None:
    rest = rest.strip()
    if rest.startswith("("):  # a tuple shape
        end = _balanced(rest, 0)
    else:
        end = rest.find(" ")
        if end < 0:
            return None
    shape, tail = rest[:end], rest[end:].lstrip()
    paren = tail.find("(")
    if paren <= 0:
        return None
    opcode = tail[:paren].strip()
    close = _balanced(tail, paren)
    operands = tuple(tok.split()[-1].lstrip("%") for tok in _split_top(tail[paren + 1 : close - 1]))
    attrs = tail[close:]
    called = list(_CALLED.findall(attrs))
    for group in _CALLED_SET.findall(attrs):
        called += [c.strip().lstrip("%") for c in group.split(",") if c.strip()]
    target = _TARGET.search(attrs)
    index = _INDEX.search(attrs) if opcode == "get-tuple-element" else None
    op_name = _OP_NAME.search(attrs)
    frame = _FRAME.search(attrs)
    return _Instruction(
        name=name,
        shape=shape,
        opcode=opcode,
        operands=operands,
        called=tuple(called),
        target=target.group(1) if target else None,
        index=int(index.group(1)) if index else None,
        op_name=op_name.group(1) if op_name else "",
        frame=int(frame.group(1)) if frame else None,
    )


def _sources(hlo_text: str) -> dict[int, str]:
    """Stack frame id → ``file:line (function)`` of its location (the module's source tables)."""
    tables: dict[str, dict[int, str]] = {t: {} for t in _TABLES}
    current = None
    for line in hlo_text.splitlines():
        if line in _TABLES:
            current = tables[line]
            continue
        m = re.match(r"^(\d+) (.*)$", line) if current is not None else None
        if m is None:
            current = None
            continue
        assert current is not None
        current[int(m.group(1))] = m.group(2).strip()

    def field(text: str, key: str) -> int | None:
        m = re.search(rf"\b{key}=(\d+)", text)
        return int(m.group(1)) if m else None

    out: dict[int, str] = {}
    for fid, frame in tables["StackFrames"].items():
        loc = tables["FileLocations"].get(field(frame, "file_location_id") or -1)
        if loc is None:
            continue
        file = tables["FileNames"].get(field(loc, "file_name_id") or -1, "?").strip('"')
        func = tables["FunctionNames"].get(field(loc, "function_name_id") or -1, "?").strip('"')
        marker = "/src/"
        short = file.split(marker, 1)[1] if marker in file else file
        out[fid] = f"{short}:{field(loc, 'line')} ({func})"
    return out


def _computations(hlo_text: str) -> dict[str, dict[str, _Instruction]]:
    """Computation name → its instructions by name (in program order)."""
    out: dict[str, dict[str, _Instruction]] = {}
    current: dict[str, _Instruction] | None = None
    for line in hlo_text.splitlines():
        if current is None:
            m = _HEADER.match(line)
            if m and not line.startswith((" ", "\t")):
                current = out.setdefault(m.group("name"), {})
            continue
        if line.strip() == "}" and not line.startswith((" ", "\t")):
            current = None
            continue
        m = _INSTRUCTION.match(line)
        if m:
            inst = _parse_instruction(m.group("name").lstrip("%"), m.group("rest"))
            if inst is not None:
                current[inst.name] = inst
    return out


def _batch(shape: str) -> int:
    """Batch count of a LAPACK call from its result shape.

    The product of all but the last two dimensions of the result's first array (the matrix
    operand's shape, for every jaxlib LAPACK kernel).
    """
    m = re.search(r"\[([\d,]*)\]", shape)
    if m is None or not m.group(1):
        return 1
    dims = [int(d) for d in m.group(1).split(",")]
    out = 1
    for d in dims[:-2]:
        out *= d
    return out


def _lapack_targets(
    comps: dict[str, dict[str, _Instruction]], pattern: re.Pattern[str], min_batch: int
) -> dict[str, dict[str, tuple[str, ...]]]:
    """Per computation: its LAPACK-bearing instructions → the targets they run (transitively)."""
    memo: dict[str, tuple[str, ...]] = {}

    def comp_targets(name: str, stack: frozenset[str]) -> tuple[str, ...]:
        if name in memo:
            return memo[name]
        if name in stack or name not in comps:
            return ()
        found: list[str] = []
        for inst in comps[name].values():
            found += inst_targets(inst, stack | {name})
        memo[name] = tuple(sorted(set(found)))
        return memo[name]

    def inst_targets(inst: _Instruction, stack: frozenset[str]) -> list[str]:
        own = []
        if inst.target and pattern.search(inst.target) and _batch(inst.shape) >= min_batch:
            own.append(f"{inst.target}[{_batch(inst.shape)}]")
        for c in inst.called:
            own += comp_targets(c, stack)
        return own

    out: dict[str, dict[str, tuple[str, ...]]] = {}
    for cname, insts in comps.items():
        bearing = {}
        for inst in insts.values():
            t = inst_targets(inst, frozenset({cname}))
            if t:
                bearing[inst.name] = tuple(sorted(set(t)))
        out[cname] = bearing
    return out


def _predecessors(insts: dict[str, _Instruction]) -> dict[str, tuple[str, ...]]:
    """Buffer-level dataflow predecessors (tuple and opt-barrier elements looked through)."""

    def element(name: str, i: int) -> tuple[str, ...]:
        src = insts.get(name)
        if src is None:
            return ()
        if src.opcode == "tuple" and i < len(src.operands):
            return (src.operands[i],)
        if src.opcode == "opt-barrier" and src.operands:
            return element(src.operands[0], i)
        return (name,)

    preds: dict[str, tuple[str, ...]] = {}
    for inst in insts.values():
        if inst.opcode == "get-tuple-element" and inst.index is not None and inst.operands:
            ps = element(inst.operands[0], inst.index)
        else:
            ps = inst.operands
        preds[inst.name] = tuple(p for p in ps if p in insts)
    return preds


def _ancestors(start: str, preds: dict[str, tuple[str, ...]]) -> set[str]:
    seen: set[str] = set()
    todo = list(preds.get(start, ()))
    while todo:
        n = todo.pop()
        if n not in seen:
            seen.add(n)
            todo.extend(preds.get(n, ()))
    return seen


def lapack_calls(hlo_text: str, *, pattern: str | re.Pattern[str] = LAPACK_TARGET) -> list[str]:
    """The LAPACK custom-call targets in an HLO module's text, one entry per call."""
    pat = re.compile(pattern) if isinstance(pattern, str) else pattern
    return [
        inst.target
        for insts in _computations(hlo_text).values()
        for inst in insts.values()
        if inst.opcode == "custom-call" and inst.target and pat.search(inst.target)
    ]


def lapack_concurrency(
    hlo_text: str,
    *,
    module: str | None = None,
    pattern: str | re.Pattern[str] = LAPACK_TARGET,
    min_batch: int = 2,
) -> list[ConcurrentLapack]:
    """Every pair of LAPACK-bearing instructions that may run concurrently (module docs).

    Args:
        hlo_text: an optimised HLO module as text (``compiled.as_text()`` or a dump's
            ``*after_optimizations.txt``).
        module: the name reported (default: the ``HloModule`` line's).
        pattern: regular expression of the custom-call targets that count (default ``^lapack_``).
        min_batch: the smallest batch count that counts (default 2: a call on one matrix runs
            inline on its thread in jaxlib — its chunk covers the batch — and cannot block).

    Returns:
        The findings, in program order; empty when every LAPACK call is ordered after or before
        every other one of its computation.
    """
    pat = re.compile(pattern) if isinstance(pattern, str) else pattern
    header = re.search(r"^HloModule\s+([^\s,]+)", hlo_text, re.MULTILINE)
    name = module if module is not None else (header.group(1) if header else "<module>")
    comps = _computations(hlo_text)
    bearing = _lapack_targets(comps, pat, min_batch)
    sources = _sources(hlo_text)

    def where(inst: _Instruction) -> str:
        return sources.get(inst.frame, inst.op_name) if inst.frame is not None else inst.op_name

    findings: list[ConcurrentLapack] = []
    for cname, insts in comps.items():
        names = list(bearing[cname])
        if len(names) < 2:
            continue
        preds = _predecessors(insts)
        anc = {n: _ancestors(n, preds) for n in names}
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                if a not in anc[b] and b not in anc[a]:
                    findings.append(
                        ConcurrentLapack(
                            module=name,
                            computation=cname,
                            first=a,
                            second=b,
                            first_targets=bearing[cname][a],
                            second_targets=bearing[cname][b],
                            first_op=where(insts[a]),
                            second_op=where(insts[b]),
                        )
                    )
    return findings


def compiled_hlo(fn, *args, **kwargs) -> str:
    """The optimised HLO text of ``fn`` compiled for these arguments (nothing is run).

    ``fn`` is a ``jax.jit`` or ``eqx.filter_jit`` function.
    """
    compiled = fn.lower(*args, **kwargs).compile()
    inner = getattr(compiled, "compiled", compiled)  # Equinox wraps jax.stages.Compiled
    return inner.as_text()


def _dump_files(folder: str | Path) -> Iterator[Path]:
    yield from sorted(Path(folder).glob("*after_optimizations.txt"))


def audit_dump(
    folder: str | Path | Iterable[str | Path],
    *,
    pattern: str | re.Pattern[str] = LAPACK_TARGET,
    min_batch: int = 2,
) -> tuple[list[ConcurrentLapack], int, int]:
    """:func:`lapack_concurrency` over every ``*after_optimizations.txt`` of an XLA dump folder.

    Returns:
        (findings, the number of modules read, the number of LAPACK custom calls in them).
    """
    folders = [folder] if isinstance(folder, str | Path) else list(folder)
    findings: list[ConcurrentLapack] = []
    modules = calls = 0
    for f in folders:
        for path in _dump_files(f):
            text = path.read_text()
            modules += 1
            calls += len(lapack_calls(text, pattern=pattern))
            stem = path.name.removesuffix(".txt")
            findings += lapack_concurrency(text, module=stem, pattern=pattern, min_batch=min_batch)
    return findings, modules, calls
