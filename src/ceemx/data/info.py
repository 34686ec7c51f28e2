"""What a record says besides its numbers: sample time, channel names and units (:class:`DataInfo`).

A :class:`DataInfo` travels with :class:`~ceemx.data.trajectories.Trajectories` as its ``info``
field, a static field of the pytree: it is hashable and compared by value, so a compiled
function that receives the data is traced once per distinct ``info`` and never because of it
otherwise (equal metadata, same program). Slicing, :meth:`~ceemx.Trajectories.windows`,
:meth:`~ceemx.Trajectories.head` and the ``with_*`` helpers keep it; helpers that change the
channels (:func:`ceemx.foh_inputs`, a constant input) rename them to match.

What reads it: :func:`ceemx.benchmark_score`'s table labels the outputs with their names and
units, and :func:`ceemx.save` stores it beside the model.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

__all__ = ["DataInfo"]


def _names(field: str, value) -> tuple[str, ...] | None:
    """``None``, or the names as a tuple of strings (one string: one channel)."""
    if value is None:
        return None
    items = (value,) if isinstance(value, str) else tuple(value)
    if not all(isinstance(v, str) for v in items):
        raise TypeError(f"`{field}` must be strings; got {value!r}.")
    return items


@dataclasses.dataclass(frozen=True)
class DataInfo:
    """Metadata of a batch of records: sample time, names and units of the channels.

    Every field is optional; names and units are tuples with one entry per channel (a single
    string is taken as one channel). Immutable and hashable (a static field of
    :class:`~ceemx.Trajectories`: ``jax.jit`` compares it by value and does not retrace on it).

    Attributes:
        dt: the sample time, in ``time_unit`` (``None``: not given).
        time_unit: the unit of ``dt`` and of time axes.
        output_names: one name per output (y), e.g. ``("h2",)``.
        output_units: one unit per output, e.g. ``("V",)``.
        input_names: one name per input (u).
        input_units: one unit per input.

    Raises:
        TypeError: a name or unit that is not a string.
        ValueError: a ``dt`` that is not a positive finite number.

    Example:
        >>> info = DataInfo(dt=4.0, output_names="h2", output_units="V")
        >>> info.output_labels(1)
        ('h2 [V]',)
    """

    dt: float | None = None
    time_unit: str = "s"
    # a string or a sequence of strings as given (one string: one channel), a tuple once built
    output_names: Sequence[str] | None = None
    output_units: Sequence[str] | None = None
    input_names: Sequence[str] | None = None
    input_units: Sequence[str] | None = None

    def __post_init__(self):
        for field in ("output_names", "output_units", "input_names", "input_units"):
            object.__setattr__(self, field, _names(field, getattr(self, field)))
        if self.dt is not None:
            try:
                dt = float(self.dt)
            except (TypeError, ValueError):
                raise TypeError(f"`dt` must be a number; got {self.dt!r}.") from None
            if not (dt > 0 and dt < float("inf")):
                raise ValueError(f"`dt` must be a positive finite sample time; got {self.dt!r}.")
            object.__setattr__(self, "dt", dt)
        if not isinstance(self.time_unit, str):
            raise TypeError(f"`time_unit` must be a string; got {self.time_unit!r}.")

    def check(self, m: int, p: int) -> None:
        """Raise ``ValueError`` when a name or unit list does not have one entry per channel."""
        for field, count, what in (
            ("output_names", m, "outputs"),
            ("output_units", m, "outputs"),
            ("input_names", p, "inputs"),
            ("input_units", p, "inputs"),
        ):
            value = getattr(self, field)
            if value is not None and len(value) != count:
                raise ValueError(
                    f"`{field}` has {len(value)} entries but the data have {count} {what}: "
                    f"{value!r}."
                )

    def output_labels(self, m: int, *, units: bool = True) -> tuple[str, ...]:
        """``m`` labels of the outputs: ``name [unit]``; ``y1``, ``y2``, … where unnamed.

        ``units=False``: the names alone (for errors not in the data's units).
        """
        return _labels(self.output_names, self.output_units if units else None, m, "y")

    def input_labels(self, p: int) -> tuple[str, ...]:
        """``p`` labels of the inputs: ``name [unit]``; ``u1``, ``u2``, … where unnamed."""
        return _labels(self.input_names, self.input_units, p, "u")

    def replace(self, **changes) -> DataInfo:
        """A copy with ``changes`` (field names as keyword arguments)."""
        return dataclasses.replace(self, **changes)

    def with_more_inputs(self, names: Sequence[str], units: Sequence[str]) -> DataInfo:
        """The info of the same data with inputs appended (``names`` and ``units`` of the new ones).

        Where the inputs had no names (units), the new ones get none either: the labels then
        default to ``u1``, ``u2``, … for every input.
        """
        return self.replace(
            input_names=None if self.input_names is None else (*self.input_names, *names),
            input_units=None if self.input_units is None else (*self.input_units, *units),
        )

    def to_dict(self) -> dict[str, Any]:
        """The fields as JSON-friendly values (lists for tuples); :meth:`from_dict` inverts it."""
        return {
            f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v
            for f in dataclasses.fields(self)
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> DataInfo:
        """The :class:`DataInfo` of :meth:`to_dict`'s output (unknown keys are refused)."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown DataInfo fields {sorted(unknown)}.")
        return cls(**values)


def _labels(names, units, count: int, letter: str) -> tuple[str, ...]:
    base = [f"{letter}{j + 1}" for j in range(count)] if names is None else list(names)
    if units is not None:
        base = [f"{n} [{u}]" if u else n for n, u in zip(base, units, strict=True)]
    return tuple(base)
