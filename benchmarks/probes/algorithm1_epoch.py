"""Algorithm-1 epoch on the Figure-3 problem: smoothing vs learning, and the learner's step bound.

    python benchmarks/probes/algorithm1_epoch.py

6 coupled Lorenz, B = 8, T = 128, seed 42, the paper's weighting, states started at truth +
N(0, 1) as ``ceemx experiment figure3``. For LM learners with ``max_steps`` 100, 2, 1 and the
L-BFGS learner: median seconds per epoch, in smoothing and in learning (epochs 2–8), and ε(θ)
after each epoch. Record ``uptime`` beside it.

Backs: ``benchmarks/README.md`` ("Figure-3 problem vs the authors' code", profile of the
Algorithm-1 epoch: "smoothing 0.12 s ..., learning 0.87 s with the LM learner", "``max_steps=1``
**0.379 s**", "L-BFGS 0.321 s (**14.4×**)").
"""

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
import ceemx  # noqa: E402
from ceemx.evaluation import metrics as ev  # noqa: E402
from ceemx.experiments import common, figure3  # noqa: E402
from ceemx.models import with_noise  # noqa: E402

true = common.true_lorenz(6)
p = common.lorenz_problem(42, true, B=8, T=128, sigma_w=0.0, sigma_v=0.01, coupling=True)
pn, on, rho_x = figure3.fit_setup("paper")
system = with_noise(p.init_system, pn, on)
k_x = jax.random.fold_in(jax.random.PRNGKey(42), 1)
x_init = p.states + jax.random.normal(k_x, p.states.shape, p.states.dtype)
learners = {
    "lm (max_steps 100)": ceemx.LMLearner(),
    "lm (max_steps 2)": ceemx.LMLearner(max_steps=2),
    "lm (max_steps 1)": ceemx.LMLearner(max_steps=1),
    "lbfgs (100 steps)": figure3.make_learner("lbfgs"),
}
for name, learner in learners.items():
    eps = ev.DynamicsErrorCallback(true)
    solver = ceemx.Alternating(smoother=ceemx.LMSmoother(rho_x=rho_x), learner=learner, rtol=0.0)
    res = ceemx.fit(
        system,
        p.data,
        x_init,
        solver=solver,
        trainable=common.LORENZ_PARAMS_H,
        max_epochs=8,
        progress=False,
        callbacks=[eps],
    )
    h = res.history[1:]
    med = {k: float(np.median([x[k] for x in h])) for k in ("time", "smooth_time", "learn_time")}
    print(
        f"{name:20s} epoch {med['time']:.3f} s (smoothing {med['smooth_time']:.3f}, learning "
        f"{med['learn_time']:.3f}); ε per epoch {[round(x['eps'], 3) for x in res.history]}"
    )
