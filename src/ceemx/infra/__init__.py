"""Infrastructure: what a fit needs around the mathematics, not in it.

Atomic checkpoints (:mod:`~ceemx.infra.checkpoint`), the persistent compilation cache
(:mod:`~ceemx.infra.compilation`), CPU thread limits for busy machines
(:mod:`~ceemx.infra.runtime`), the memory guard (:mod:`~ceemx.infra.memory`) and warnings
attributed to the user's line (:mod:`~ceemx.infra.warn`). Layer rule: may import :mod:`ceemx.lib`
only; every other layer may import it.
"""
