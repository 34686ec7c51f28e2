"""Warnings attributed to the user's code: the first frame outside ceemx."""

from __future__ import annotations

import sys
import warnings

__all__ = ["warn"]

# Frames that are never the caller: ceemx itself, the runtime type-checking wrappers that the
# test suite puts around ceemx's functions (jaxtyping, beartype), and Equinox's method wrappers
# (a ceemx method called through a module's bound-method wrapper).
_INTERNAL_MODULES = ("ceemx", "jaxtyping", "beartype", "equinox")


def _is_internal(frame) -> bool:
    module = frame.f_globals.get("__name__") or ""
    if module.split(".")[0] in _INTERNAL_MODULES:
        return True
    # Wrappers generated at run time (e.g. "<@beartype(ceemx.fit) at 0x...>") have no module.
    filename = frame.f_code.co_filename
    return filename.startswith("<@beartype") or any(
        f"/{name}/" in filename for name in _INTERNAL_MODULES[1:]
    )


def warn(message: str, category: type[Warning] = UserWarning) -> None:
    """``warnings.warn`` with the stack level of the first caller outside ceemx.

    A fixed ``stacklevel`` breaks whenever a call goes through one more ceemx function or a
    decorator's wrapper; this walks the stack instead.
    """
    frame = sys._getframe(0)
    level = 1
    while frame.f_back is not None and _is_internal(frame):
        frame = frame.f_back
        level += 1
    warnings.warn(message, category, stacklevel=level)
