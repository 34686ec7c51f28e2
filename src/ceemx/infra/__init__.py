"""Infrastructure: what a fit needs around the mathematics, not in it.

How programs are compiled and run on this machine — one-shot or optimised, compiled ahead or
not, BLAS threads — is decided in one place (:mod:`~ceemx.infra.policy`), over the compile
mechanisms and the persistent cache (:mod:`~ceemx.infra.compilation`) and the thread limits for
busy machines (:mod:`~ceemx.infra.runtime`). Beside them: atomic checkpoints
(:mod:`~ceemx.infra.checkpoint`) and their one-writer lock (:mod:`~ceemx.infra.folder_lock`), one
fit over several processes (:mod:`~ceemx.infra.distributed`: ``jax.distributed`` set-up, host
reads, a launcher), the memory guard (:mod:`~ceemx.infra.memory`), the validation of solver and
learner options (:mod:`~ceemx.infra.options`), warnings attributed to the user's line
(:mod:`~ceemx.infra.warn`) and output folders checked before any compute
(:mod:`~ceemx.infra.paths`, light enough for the command line's argument checks), and how the
command ends on SIGINT or SIGTERM (:mod:`~ceemx.infra.interrupts`, as light).
Layer rule: may import :mod:`ceemx.lib` only; every other layer may import it.
"""
