"""The speed table: every speed claim of ``benchmarks/README.md`` re-measured in one run, beside
the authors' code where a row has it.

    bash benchmarks/reference/setup.sh                      # once: the authors' code
    python benchmarks/speed_table.py [--only ROW ...] [--skip ROW ...] [--before REV]
    python benchmarks/speed_table.py --table-only            # the table from the committed JSON

Each row is one of the committed scripts, run as a subprocess in turn (they alternate ceemx and
the reference inside, median of ≥ 3; the 1-minute load is recorded before and after each), and
writes its own canonical JSON in ``benchmarks/results``:

- ``figure3``: ``compare_reference_figure3.py --reps 3 --epochs 5 --methods alternate`` — the
  Figure-3 Algorithm-1 epoch (B = 8, 342 parameters) against the authors' code;
- ``lorenz_cold``: ``compare_reference.py --reps 3`` — the single-Lorenz first fit in a fresh
  process (no persistent cache), the steady fits and the whole 5-seed process;
- ``lorenz_warm``: the same with ``--cache DIR``, twice (the first run fills the cache; the second
  is the row): the first fit with the persistent compilation cache warm;
- ``demo``: ``demo_latency.py --reps 3`` — ``ceemx demo`` cold and warm;
- ``k100``: ``k100.py`` — K = 100 coupled Lorenz (n = 300, P = 90 300), ε after each epoch
  within 600 s;
- ``laplace``: ``laplace_long_record.py --T 100000 --reps 3`` — Laplace EM on one 10⁵-sample
  record beside a JointLM fit in the same run;
- ``multi_process``: ``multi_process.py --rounds 2`` — two processes against one, θ and J;
- ``parallel``: ``parallel_in_time.py`` — the parallel-in-time block solve against the
  sequential scans (CPU);
- ``long``: ``scaling.py --only long --quick --long-T 10000 31623 100000`` — time and memory
  against T for one record.

``--before REV``: ``git archive REV`` unpacked in a temporary folder and passed as
``--before-src`` to the scripts that take it (an earlier tree beside this one, same run).
``speed_table.json`` in ``--out-dir`` (default ``benchmarks/results``) records the commands, the
load and the wall time per row; the table is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
#: each row's JSON, as its script writes it by default.
OUTPUTS = {
    "figure3": "compare_reference_figure3.json",
    "lorenz_cold": "compare_reference.json",
    "lorenz_warm": "compare_reference_warm_cache.json",
    "demo": "demo_latency.json",
    "k100": "k100.json",
    "laplace": "laplace_long_record.json",
    "multi_process": "multi_process.json",
    "parallel": "parallel_in_time.json",
    "long": "scaling_long.json",
}
ROWS = (
    "figure3",
    "lorenz_cold",
    "lorenz_warm",
    "demo",
    "k100",
    "laplace",
    "multi_process",
    "parallel",
    "long",
)


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def before_tree(rev: str, tmp: pathlib.Path) -> pathlib.Path:
    dest = tmp / "before"
    dest.mkdir()
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", rev], capture_output=True, check=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest / "src"


def commands(
    out: pathlib.Path, before: str | None, cache: pathlib.Path
) -> dict[str, list[list[str]]]:
    py = [sys.executable]
    b = ["--before-src", before] if before else []
    return {
        "figure3": [
            py
            + [
                str(HERE / "compare_reference_figure3.py"),
                "--reps",
                "3",
                "--epochs",
                "5",
                "--methods",
                "alternate",
                *b,
                "--out",
                str(out / OUTPUTS["figure3"]),
            ]
        ],
        "lorenz_cold": [
            py
            + [
                str(HERE / "compare_reference.py"),
                "--reps",
                "3",
                *b,
                "--out",
                str(out / OUTPUTS["lorenz_cold"]),
            ]
        ],
        "lorenz_warm": [
            py
            + [
                str(HERE / "compare_reference.py"),
                "--reps",
                "1",
                "--cache",
                str(cache),
                *b,
                "--out",
                str(cache.parent / "fill.json"),
            ],
            py
            + [
                str(HERE / "compare_reference.py"),
                "--reps",
                "3",
                "--cache",
                str(cache),
                *b,
                "--out",
                str(out / OUTPUTS["lorenz_warm"]),
            ],
        ],
        "demo": [
            py
            + [
                str(HERE / "demo_latency.py"),
                "--reps",
                "3",
                *b,
                "--out",
                str(out / OUTPUTS["demo"]),
            ]
        ],
        "k100": [py + [str(HERE / "k100.py"), "--out", str(out / OUTPUTS["k100"])]],
        "laplace": [
            py
            + [
                str(HERE / "laplace_long_record.py"),
                "--T",
                "100000",
                "--reps",
                "3",
                "--out",
                str(out / OUTPUTS["laplace"]),
            ]
        ],
        "multi_process": [
            py
            + [
                str(HERE / "multi_process.py"),
                "--rounds",
                "2",
                "--out",
                str(out / OUTPUTS["multi_process"]),
            ]
        ],
        "parallel": [
            py + [str(HERE / "parallel_in_time.py"), "--out", str(out / OUTPUTS["parallel"])]
        ],
        "long": [
            py
            + [
                str(HERE / "scaling.py"),
                "--only",
                "long",
                "--quick",
                "--long-T",
                "10000",
                "31623",
                "100000",
                "--out",
                str(out / OUTPUTS["long"]),
            ]
        ],
    }


def _load(path: pathlib.Path) -> dict | None:
    return json.loads(path.read_text()) if path.exists() else None


def table(out: pathlib.Path, log: dict) -> str:
    """The speed table from the rows' JSON (rows not run are left out)."""
    lines = [
        "| measure | authors' code | before | ceemx | target | met |",
        "|---|---|---|---|---|---|",
    ]

    def row(*cells):
        lines.append("| " + " | ".join(cells) + " |")

    f3 = _load(out / OUTPUTS["figure3"])
    if f3:
        s = f3["summary"]
        ref, aft, bef = s["reference"], s["alternate"], s.get("alternate_before", {})
        ratio = ref["epoch_s_median"] / aft["epoch_s_median"]
        row(
            "Figure-3 Algorithm-1 epoch (B = 8, 342 parameters), steady",
            f"{ref['epoch_s_median']:.2f} s",
            f"{bef['epoch_s_median']:.3f} s ({ref['epoch_s_median'] / bef['epoch_s_median']:.1f}×)"
            if bef
            else "—",
            f"{aft['epoch_s_median']:.3f} s ({ratio:.1f}×)",
            "≥ 20×",
            "yes" if ratio >= 20 else "no",
        )
        row(
            "  ε after 5 epochs (same start)",
            f"{ref['eps_per_epoch'][-1]:.3f}",
            f"{bef['eps_per_epoch'][-1]:.3f}" if bef else "—",
            f"{aft['eps_per_epoch'][-1]:.3f}",
            "—",
            "—",
        )
    for name, label, target in (("lorenz_cold", "cold", 3.0), ("lorenz_warm", "warm cache", 0.5)):
        d = _load(out / OUTPUTS[name])
        if not d:
            continue
        s = d["summary"]
        ref, j = s["reference"]["fit_s_median"], s["joint"]["first_fit_s_median"]
        jb = s.get("joint_before", {}).get("first_fit_s_median")
        row(
            f"single-Lorenz JointLM, first fit in a fresh process ({label})",
            f"{ref:.2f} s per fit",
            f"{jb:.2f} s" if jb else "—",
            f"{j:.2f} s",
            f"≤ {target} s",
            "yes" if j <= target else "no",
        )
        if name == "lorenz_cold":
            pr, pc = s["reference"]["process_s_median"], s["ceemx_process_s_median"]
            pb = s.get("ceemx_process_s_median_before")
            row(
                "  whole process, 5 seeds (5 JointLM + 5 Algorithm 1)",
                f"{pr:.2f} s",
                f"{pb:.2f} s ({pr / pb:.2f}×)" if pb else "—",
                f"{pc:.2f} s ({pr / pc:.2f}×)",
                "≥ 2×",
                "yes" if pr / pc >= 2 else "no",
            )
            row(
                "  steady fit JointLM / Algorithm 1",
                f"{ref:.2f} s",
                "—",
                f"{s['joint']['warm_fit_s_median']:.3f} / {s['alternate']['warm_fit_s_median']:.3f}"
                " s",
                "—",
                "—",
            )
    d = _load(out / OUTPUTS["demo"])
    if d:
        a, b = d["summary"]["after"], d["summary"].get("before")
        row(
            "`ceemx demo`, cold / warm cache",
            "—",
            f"{b['cold']:.1f} / {b['warm']:.1f} s" if b else "—",
            f"{a['cold']:.1f} / {a['warm']:.1f} s",
            "≤ 8 s cold",
            "yes" if a["cold"] <= 8 else "no",
        )
    d = _load(out / OUTPUTS["k100"])
    if d:
        eps = [f"{e['eps'] / d['eps_initial']:.2%} at {e['wall_s']:.0f} s" for e in d["epochs"]]
        row(
            "K = 100 coupled Lorenz (n = 300, P ≈ 90 000), ε / ε₀ after each epoch",
            "—",
            "—",
            "; ".join(eps) + f" (total {d['total_wall_s']:.0f} s)",
            "≤ 1 % in 10 min",
            "yes" if d.get("target_met") else "no",
        )
    d = _load(out / OUTPUTS["laplace"])
    if d:
        med = d["runs"][0]["summary"]
        jl, qn, sq = (med[k]["median_fit_s"] for k in ("joint_lm", "laplace_em_qn", "laplace_em"))
        row(
            "Laplace EM (learned noise), one 100 000-sample record: quasi-Newton / SQUAREM "
            "(the default)",
            "—",
            "—",
            f"{qn:.2f} / {sq:.1f} s against JointLM {jl:.2f} s ({qn / jl:.2f}× / {sq / jl:.1f}×)",
            "≤ 3× a JointLM fit",
            "quasi-Newton: "
            + ("yes" if qn / jl <= 3 else "no")
            + "; SQUAREM: "
            + ("yes" if sq / jl <= 3 else "no"),
        )
    d = _load(out / OUTPUTS["multi_process"])
    if d:
        row(
            "two processes (Gloo) against one: θ, J relative difference; steady epoch 1 / 2 "
            "processes",
            "joblib",
            "—",
            f"{d['theta_relative_difference']:.1e}, {d['J_relative_difference']:.1e}; "
            f"{d['median_steady_s']['1']:.3f} / {d['median_steady_s']['2']:.3f} s",
            "same θ as one process (1e-10)",
            "yes" if d["theta_relative_difference"] <= 1e-10 else "no",
        )
    d = _load(out / OUTPUTS["parallel"])
    if d:
        worst = max(c["rel_diff"] for c in d["cases"])
        big = [c for c in d["cases"] if c["T"] == max(x["T"] for x in d["cases"])]
        row(
            "parallel-in-time block solve (CPU): largest difference to sequential; T = 10⁵ "
            "parallel / sequential",
            "—",
            "—",
            f"{worst:.1e}; "
            + ", ".join(
                f"n = {c['n']}: {1e3 * c['parallel']['median_s']:.0f} / "
                f"{1e3 * c['sequential']['median_s']:.0f} ms"
                for c in big
            ),
            "equal to sequential (1e-8); < 50 ms on a GPU",
            "equal: yes; GPU: not lent",
        )
    d = _load(out / OUTPUTS["long"])
    if d:
        fits, met = d["long"]["fits"], d["long"]["target"]["met"]
        ms = list(fits)
        row(
            f"one record, T = 10⁴…10⁵ ({' / '.join(ms)}): log–log slope of the time per "
            "iteration, all T (two largest)",
            "—",
            "—",
            " / ".join(
                f"{fits[m]['time_per_iteration']['slope']:.2f} "
                f"({fits[m]['time_per_iteration_top']['slope']:.2f})"
                for m in ms
            ),
            "≤ 1.15 (linear)",
            " / ".join("yes" if met[m]["time"] else "no" for m in ms),
        )
        row(
            "  the same, memory: slope of the steady calls' peak increment",
            "—",
            "—",
            " / ".join(f"{fits[m]['steady_peak_increment']['slope']:.2f}" for m in ms),
            "≤ 1.15",
            " / ".join("yes" if met[m]["memory"] else "no" for m in ms),
        )
    lines.append("")
    lines.append("Load (1-min) and wall time per row:")
    for name, entry in log.items():
        lines.append(
            f"- {name}: {entry['wall_s']:.0f} s; before: {entry['uptime_before']}; "
            f"after: {entry['uptime_after']}; rc {entry['rc']}"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out-dir", default=str(HERE / "results"))
    ap.add_argument("--before", default=None, help="git revision of an earlier tree to run beside")
    ap.add_argument("--only", nargs="+", choices=ROWS, default=None)
    ap.add_argument("--skip", nargs="+", choices=ROWS, default=())
    ap.add_argument("--table-only", action="store_true", help="the table from the committed JSON")
    args = ap.parse_args()
    out = pathlib.Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "speed_table.json"
    log = (_load(log_path) or {}).get("rows", {})
    if not args.table_only:
        rows = [r for r in (args.only or ROWS) if r not in args.skip]
        with tempfile.TemporaryDirectory() as tmp_name:
            tmp = pathlib.Path(tmp_name)
            before = str(before_tree(args.before, tmp)) if args.before else None
            cmds = commands(out, before, tmp / "cache")
            for name in rows:
                entry = {"uptime_before": uptime(), "commands": [], "rc": 0}
                t0 = time.perf_counter()
                for cmd in cmds[name]:
                    print(f"== {name}: {' '.join(cmd[1:])}", flush=True)
                    env = dict(os.environ, MPLBACKEND="Agg")
                    proc = subprocess.run(cmd, env=env, cwd=ROOT)
                    entry["commands"].append(
                        " ".join(
                            ["python"]
                            + [
                                os.path.relpath(c, ROOT) if c.startswith(str(ROOT)) else c
                                for c in cmd[1:]
                            ]
                        )
                    )
                    entry["rc"] = entry["rc"] or proc.returncode
                entry["wall_s"] = time.perf_counter() - t0
                entry["uptime_after"] = uptime()
                log[name] = entry
                log_path.write_text(json.dumps({"before": args.before, "rows": log}, indent=1))
    print(table(out, log))


if __name__ == "__main__":
    main()
