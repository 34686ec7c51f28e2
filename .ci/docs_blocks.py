"""Docs as tests: every Python block of README.md and docs/**/*.md runs as written, in order.

Each page runs in a fresh Python process, in an empty temporary folder (files the page writes go
there), its blocks one after another in one namespace, as a reader pasting them into one script
would. A block's output is what it prints to stdout, then one ``Category: message`` line per
distinct warning it raised (what a reader sees on the terminal, without the source lines).

The page's text shows outputs as ```` ```text ```` fences: each one is the output of the Python
block before it (a text fence before any Python block, or two after one block, is an error).
``--check`` (the default) compares them with the run — the words exactly (whitespace runs are one
space: a wrapped table line is the same line), numbers to a relative 1e-3, wall-clock times
(``12.3 s``, ``0.5 ms``) and timestamps not at all; a block that warns without a text fence is an
error (the reader would see a warning the page does not show). ``--write`` puts the run's outputs
into the pages instead: the committed command that regenerates every printed output.

A block that loads a real dataset (``datasets.cascaded_tanks()`` and the like) runs only when the
data file is on disk (``CEEMX_DATA``, which this runner points at ``../shared/data`` when it is
unset and that folder exists; the download cache): otherwise it and the rest of its page are not
run, said so (the blocks before it run). A block
preceded by ``<!-- docs-test: skip REASON -->`` is not run (the reason is reported): a reproducer
of a hang, a block that needs a package ceemx does not depend on.

Usage::

    .venv/bin/python .ci/docs_blocks.py [--write] [--jobs N] [PAGE ...]

No environment knob shortens a page: every block runs as a reader runs it.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
import traceback
import types
import warnings
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^```(\S*)[^\n]*\n(.*?)^```[ \t]*$", re.S | re.M)
DIRECTIVE = re.compile(r"<!--\s*docs-test:\s*skip\s+(.*?)\s*-->\s*$")
DATASET = re.compile(r"datasets\.(cascaded_tanks|silverbox|coupled_electric_drives)\(")
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
# Wall-clock times and timestamps vary from run to run and machine to machine: not compared.
VOLATILE = (
    re.compile(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(?:\.\d+)?(?:[+-]\d\d:\d\d|Z)?"),
    re.compile(r"(?<![=\w.+-])(?<!= )(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?\s*(?:s|ms|min)\b"),
)
RTOL = 1e-3


@dataclass
class Block:
    """One ```` ```python ```` fence, with the ```` ```text ```` fence showing its output."""

    line: int  # the first code line, 1-based
    code: str
    skip: str | None = None
    output: str | None = None
    output_span: tuple[int, int] | None = None  # character span of the output fence's body


@dataclass
class Page:
    """A page's Python blocks in order and the datasets its code loads."""

    path: Path
    blocks: list[Block] = field(default_factory=list)

    @property
    def datasets(self) -> list[str]:
        """The real datasets the page's blocks load (``datasets.silverbox()`` and the like)."""
        found = {m for b in self.blocks if b.skip is None for m in DATASET.findall(b.code)}
        return sorted(found)


def pages() -> list[Path]:
    """README.md and every page of the documentation site."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def parse(path: Path, text: str | None = None) -> Page:
    """The page's Python blocks, each with its skip directive and its output fence."""
    text = path.read_text() if text is None else text
    page = Page(path)
    for m in FENCE.finditer(text):
        lang = m.group(1).lower()
        if lang == "python":
            before = text[: m.start()].rstrip("\n").rsplit("\n", 1)[-1]
            directive = DIRECTIVE.search(before)
            line = text.count("\n", 0, m.start(2)) + 1
            page.blocks.append(Block(line, m.group(2), directive.group(1) if directive else None))
        elif lang == "text":
            line = text.count("\n", 0, m.start()) + 1
            if not page.blocks:
                raise ValueError(f"{path.name}:{line}: a text fence before any Python block")
            block = page.blocks[-1]
            if block.output is not None:
                raise ValueError(f"{path.name}:{line}: a second text fence after one Python block")
            if block.skip is not None:
                raise ValueError(f"{path.name}:{line}: the output of a block that is not run")
            block.output, block.output_span = m.group(2), (m.start(2), m.end(2))
    return page


def _normalise(text: str) -> str:
    for pattern in VOLATILE:
        text = pattern.sub("<time>", text)
    return " ".join(text.split())


def same_output(expected: str, actual: str, rtol: float = RTOL) -> bool:
    """Whether two outputs agree: words exactly, numbers to ``rtol``, times and dates not at all."""
    a, b = _normalise(expected), _normalise(actual)
    words_a, words_b = NUMBER.split(a), NUMBER.split(b)
    if words_a != words_b:
        return False
    for x, y in zip(NUMBER.findall(a), NUMBER.findall(b), strict=True):
        if x == y:
            continue
        fx, fy = float(x), float(y)
        if not math.isclose(fx, fy, rel_tol=rtol, abs_tol=0.0):
            return False
    return True


def first_difference(expected: str, actual: str) -> str:
    """The first line where two outputs differ, for the report."""
    exp, act = expected.splitlines(), actual.splitlines()
    for i, (x, y) in enumerate(zip(exp, act, strict=False)):
        if not same_output(x, y):
            return f"line {i + 1}:\n    page: {x}\n    run:  {y}"
    return f"{len(exp)} lines on the page, {len(act)} in the run"


# The child: run one page's blocks in this process.


def _warning_lines(caught: list[warnings.WarningMessage]) -> str:
    seen: list[str] = []
    for w in caught:
        line = f"{w.category.__name__}: {w.message}"
        if line not in seen:
            seen.append(line)
    return "".join(s + "\n" for s in seen)


def run_page(path: Path) -> dict:
    """Execute the page's blocks in order in one namespace; outputs, times, the first error."""
    page = parse(path)
    result: dict = {"page": str(path), "blocks": [], "skipped": None, "error": None}
    no_data = len(page.blocks)  # the first block not run for want of data
    if page.datasets:
        from ceemx.datasets import data_file

        for name in page.datasets:
            try:
                data_file(name, download=False)
            except FileNotFoundError as e:
                result["skipped"] = f"needs the {name} data ({str(e).split(':')[0]})"
                loads = [b.skip is None and bool(DATASET.search(b.code)) for b in page.blocks]
                no_data = loads.index(True)
                break
    # The blocks run as one script would: in a module that is ``__main__`` (so that a class the
    # page defines is found by name, as ``ceemx.save`` looks it up).
    script = types.ModuleType("__main__")
    script.__file__ = str(path)
    sys.modules["__main__"] = script
    namespace = script.__dict__
    for i, block in enumerate(page.blocks):
        entry: dict = {"line": block.line, "skip": block.skip}
        result["blocks"].append(entry)
        if i >= no_data:  # this block loads the data or follows one that does
            entry["skip"] = result["skipped"]
        if entry["skip"] is not None:
            continue
        code = compile("\n" * (block.line - 1) + block.code, str(path), "exec")
        out = io.StringIO()
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stdout(out):
                warnings.simplefilter("always")
                exec(code, namespace)
        except BaseException:
            result["error"] = f"block at line {block.line}:\n{traceback.format_exc()}"
            entry["output"] = out.getvalue()
            return result
        finally:
            entry["seconds"] = time.perf_counter() - t0
        entry["output"] = out.getvalue() + _warning_lines(caught)
        entry["warned"] = bool(caught)
    return result


# The parent: a process per page, compare or write, report.


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("MPLBACKEND", "Agg")
    shared = ROOT.parent / "shared" / "data"
    if "CEEMX_DATA" not in env and shared.is_dir():
        env["CEEMX_DATA"] = str(shared.resolve())
    src = str(ROOT / "src")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (src, env.get("PYTHONPATH", "")) if p)
    return env


def _launch(path: Path, folder: Path) -> tuple[subprocess.Popen, Path]:
    report = folder / "report.json"
    cwd = folder / "cwd"
    cwd.mkdir()
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(path), str(report)]
    return subprocess.Popen(cmd, cwd=cwd, env=_env()), report


def check(page: Page, run: dict, write: bool) -> tuple[list[str], int]:
    """Problems of one page's run (compared with its text fences), and the outputs checked."""
    problems, checked = [], 0
    if run["error"]:
        problems.append(run["error"])
    done = run["blocks"][:-1] if run["error"] else run["blocks"]  # the failed block: reported
    for block, entry in zip(page.blocks, done, strict=False):
        if block.skip is not None or "output" not in entry:
            continue
        if block.output is None:
            if entry.get("warned"):
                problems.append(
                    f"block at line {block.line} warns, and the page shows no output:\n"
                    + entry["output"]
                )
            continue
        checked += 1
        if not write and not same_output(block.output, entry["output"]):
            diff = first_difference(block.output, entry["output"])
            problems.append(f"output of the block at line {block.line} differs, {diff}")
    return problems, checked


def write_outputs(page: Page, run: dict) -> bool:
    """Put the run's outputs into the page's text fences; whether the page changed."""
    text = page.path.read_text()
    spans = []
    for block, entry in zip(page.blocks, run["blocks"], strict=False):
        if block.output_span is not None and "output" in entry:
            spans.append((block.output_span, entry["output"]))
    new = text
    for (start, end), output in sorted(spans, reverse=True):
        new = new[:start] + output.rstrip("\n") + "\n" + new[end:]
    if new != text:
        page.path.write_text(new)
    return new != text


def main(argv: list[str] | None = None) -> int:
    """Run the pages (all, or those named) and report; exit status 1 when any fails."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("pages", nargs="*", help="pages to run (default: all)")
    parser.add_argument("--write", action="store_true", help="write the outputs into the pages")
    parser.add_argument("--jobs", type=int, default=1, help="pages run at once")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        with open(args.child[1], "w") as f:
            json.dump(run_page(Path(args.child[0])), f)
        return 0
    paths = [Path(p).resolve() for p in args.pages] or pages()
    todo = [(p, parse(p)) for p in paths]
    todo = [(p, page) for p, page in todo if page.blocks]
    t_start = time.perf_counter()
    failed = 0
    rows = []
    with tempfile.TemporaryDirectory(prefix="ceemx-docs-") as tmp:
        queue = list(enumerate(todo))
        running: list = []
        while queue or running:
            while queue and len(running) < max(args.jobs, 1):
                i, (path, page) = queue.pop(0)
                folder = Path(tmp) / str(i)
                folder.mkdir()
                proc, report = _launch(path, folder)
                running.append((proc, report, path, page, time.perf_counter()))
            time.sleep(0.2)
            for item in list(running):
                proc, report, path, page, t0 = item
                if proc.poll() is None:
                    continue
                running.remove(item)
                name = path.relative_to(ROOT)
                seconds = time.perf_counter() - t0
                if proc.returncode != 0 or not report.exists():
                    failed += 1
                    rows.append(f"{name}: FAILED (runner exit {proc.returncode})")
                    continue
                run = json.loads(report.read_text())
                n_run = sum(1 for e in run["blocks"] if "output" in e)
                n_skip = [b.line for b in page.blocks if b.skip is not None]
                problems, checked = check(page, run, args.write)
                if args.write and not run["error"] and write_outputs(page, run):
                    checked_word = "written"
                else:
                    checked_word = "checked"
                row = (
                    f"{name}: {n_run} of {len(page.blocks)} blocks run, {checked} outputs "
                    f"{checked_word}, {seconds:.1f} s"
                )
                if n_skip:
                    row += f"; not run (directive): lines {', '.join(map(str, n_skip))}"
                if run["skipped"]:
                    first = next(e["line"] for e in run["blocks"] if e["skip"] == run["skipped"])
                    row += f"; from line {first} on not run: {run['skipped']}"
                if problems:
                    failed += 1
                    row += " — FAILED\n" + "\n".join("  " + p for p in problems)
                rows.append(row)
    for row in rows:
        print(row)
    total = time.perf_counter() - t_start
    print(f"docs blocks: {len(todo)} pages, {failed} failed, {total:.1f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
