"""Infrastructure: what a fit needs around the mathematics, not in it.

Atomic checkpoints (:mod:`~ceemx.infra.checkpoint`) and their one-writer lock
(:mod:`~ceemx.infra.folder_lock`), the persistent compilation cache
(:mod:`~ceemx.infra.compilation`), one fit over several processes
(:mod:`~ceemx.infra.distributed`: ``jax.distributed`` set-up, host reads, a launcher), CPU
thread limits for busy machines (:mod:`~ceemx.infra.runtime`), the memory guard
(:mod:`~ceemx.infra.memory`), the validation of solver and learner options
(:mod:`~ceemx.infra.options`), warnings attributed to the user's line (:mod:`~ceemx.infra.warn`)
and the audit of compiled programs for LAPACK calls that may run concurrently
(:mod:`~ceemx.infra.hlo_audit`, docs/known_issues.md); output folders checked before any compute
(:mod:`~ceemx.infra.paths`, light enough for the command line's argument checks), and how the
command ends on SIGINT or SIGTERM (:mod:`~ceemx.infra.interrupts`, as light).
Layer rule: may import :mod:`ceemx.lib` only; every other layer may import it.
"""
