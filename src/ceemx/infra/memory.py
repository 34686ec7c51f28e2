"""Refuse, before any compute, work whose dense arrays cannot fit in this machine's memory.

A dense Gauss–Newton matrix grows as P² and the joint method's border as B·T·n·P; past the
machine's memory XLA fails late with an allocation error that names neither the cause nor the
way out. :func:`check_fits` compares an estimate with the physical memory (Linux/macOS
``sysconf``; no check where that is unknown) and raises a ``ValueError`` naming the method, the
sizes and what to use instead.
"""

from __future__ import annotations

import os

__all__ = ["check_fits", "physical_memory"]


def physical_memory() -> int | None:
    """Bytes of physical memory, or ``None`` when the platform does not say."""
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None
    return int(pages) * int(size) if pages > 0 and size > 0 else None


def check_fits(what: str, nbytes: int | float, advice: str) -> None:
    """Raise ``ValueError`` when ``nbytes`` exceed the physical memory.

    Args:
        what: the arrays and their shape, e.g. "8 dense 90300 × 90300 Gauss–Newton matrices".
        nbytes: their size in bytes (an estimate of the peak).
        advice: what to use instead.
    """
    total = physical_memory()
    if total is None or nbytes <= total:
        return
    raise ValueError(
        f"{what} need about {nbytes / 2**30:.3g} GiB, more than this machine's "
        f"{total / 2**30:.3g} GiB of memory; {advice}"
    )
