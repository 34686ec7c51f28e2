"""The paper's experiments and the README demo, each ``run(*, smoke=False, out=..., ...) -> dict``.

- :mod:`~ceemx.experiments.table1` — Table 1: bias on a single Lorenz system (§4.1.1).
- :mod:`~ceemx.experiments.figure2` — Figure 2: CE-EM against Particle EM (§4.1.2).
- :mod:`~ceemx.experiments.figure3` — Figure 3: convergence on six coupled Lorenz (§4.1.3).
- :mod:`~ceemx.experiments.figure4` — Figure 4: one-step prediction with hidden states, five
  models (§4.2), on the helicopter-like generator, the paper's dataset or a real dataset.
- :mod:`~ceemx.experiments.real_data` — beyond the paper: gray-box CE-EM on the three real
  datasets (cascaded tanks, Silverbox, coupled drives), scored by the official protocol.
- :mod:`~ceemx.experiments.calibration` — beyond the paper: Laplace EM learning the noise on the
  Figure-2 setting, and the coverage of its (and CE-EM's) 95 % intervals over 100 seeds.
- :mod:`~ceemx.experiments.demo` — the README demo.

Each writes ``results.json``, a Markdown ``table.md`` (the paper's numbers beside ours) and a PNG
figure to its output folder. They enable float64 (``jax_enable_x64``) when run. Run them from the
command line with ``ceemx experiment NAME [--smoke]`` or ``ceemx demo``.
"""

from importlib import import_module

EXPERIMENTS = ("table1", "figure2", "figure3", "figure4", "real_data", "calibration")
#: The identification methods of ``--method`` (:func:`ceemx.experiments.common.make_solver`).
METHODS = ("joint", "alternate", "particle", "laplace")

__all__ = ["EXPERIMENTS", "METHODS", "get", "parse_seeds"]


def get(name: str):
    """The module of an experiment (a name of :data:`EXPERIMENTS` or ``"demo"``)."""
    if name not in (*EXPERIMENTS, "demo"):
        raise ValueError(f"unknown experiment {name!r}; choose from {', '.join(EXPERIMENTS)}.")
    return import_module(f"{__name__}.{name}")


def parse_seeds(text: str) -> int | tuple[int, ...]:
    """``--seeds`` of the command line: ``"N"`` → N (a count); ``"42,44"`` or ``"42,"`` → seeds.

    Raises:
        ValueError: when ``text`` is not a positive integer or a comma list of at least one
            integer (zero runs are an error, never an empty result).
    """
    text = text.strip()
    try:
        seeds = [int(s) for s in text.split(",") if s.strip()] if "," in text else None
        n = int(text) if seeds is None else len(seeds)
    except ValueError:
        raise ValueError(
            f"expected a count N or a comma list of integer seeds; got {text!r}."
        ) from None
    if seeds is not None:
        if not seeds:
            raise ValueError("a comma list of seeds must name at least one seed.")
        return tuple(seeds)
    if n < 1:
        raise ValueError(f"the number of seeds must be >= 1; got {n}.")
    return n
