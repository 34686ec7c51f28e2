"""How often the summary's "one-step errors" row flags a fit of the default-fit bank.

The row (``ceemx.identification.analysis.diagnostics.prediction_error_check``) tests each
output's EKF one-step prediction errors for whiteness (Box–Pierce over 25 lags at 1 %). On the
bank's records (``benchmarks/default_fit_bank.py``: the same data, starts and noise guesses) the
model is the true one, so a flag is either a fit at another maximum (its estimate far from the
truth) or the test's own false alarm (1 % per output for an exact filter; more where the EKF's
linearisation is coarse). The row's outlier test (the largest standardised error's Bonferroni
p-value below 1 %) is counted too: on these records, which hold no glitch, every flag is a false
alarm. Per seed: the default fit's estimate, each output's p-values and largest error; at the
end the flagged seeds.

Usage::

    python benchmarks/one_step_check.py --model lorenz --seeds 0-199
    python benchmarks/one_step_check.py --model stiff --seeds 0-39

Writes ``benchmarks/results/one_step_check_<model>.json``. Backs: ``docs/guarantees.md``
("The default fit").
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import ceemx  # noqa: E402
from ceemx.identification.analysis.diagnostics import (  # noqa: E402
    prediction_error_check,
)

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
import default_fit_bank as bank  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="lorenz", choices=sorted(bank.CONFIGS))
    ap.add_argument("--seeds", default="0-199", help="a range a-b or a comma list")
    args = ap.parse_args()
    cfg = bank.CONFIGS[args.model]
    rows = []
    for seed in bank.parse_seeds(args.seeds):
        data, system, _, factor = bank.problem(cfg, seed, "alternate")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = ceemx.fit(system, data, progress=False)
        check = prediction_error_check(result)
        assert check is not None
        est = {p: float(getattr(result.system, p)) for p in cfg.params}
        assert check.extremes is not None
        rows.append({"seed": seed, "factor": factor, "estimate": est, "p": list(check.p_values),
                     "largest": check.extremes.size.tolist(),
                     "outlier_p": check.extremes.p.tolist()})  # fmt: skip
        flag = ("" if check.white else "  NOT white") + ("  OUTLIER" if check.outliers else "")
        largest = ", ".join(f"{z:.3g}" for z in check.extremes.size)
        ps = ", ".join(f"{p:.2g}" for p in check.p_values)
        print(f"{seed}: p = {ps}, largest {largest}{flag}", flush=True)
    flagged = [r["seed"] for r in rows if min(r["p"]) < 0.01]
    outliers = [r["seed"] for r in rows if min(r["outlier_p"]) < 0.01]
    print(f"{args.model}: {len(flagged)} of {len(rows)} fits flagged not white: seeds {flagged}")
    print(f"{args.model}: {len(outliers)} of {len(rows)} fits flagged an outlier: seeds {outliers}")
    out = ROOT / "results" / f"one_step_check_{args.model}.json"
    meta = {"command": " ".join(["benchmarks/one_step_check.py", *sys.argv[1:]]),
            "machine": bank.machine()}  # fmt: skip
    out.write_text(json.dumps({"meta": meta, "flagged": flagged, "outliers": outliers,
                               "rows": rows}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
