"""Exceptions raised by closedchain.

Every error derives from :class:`ClosedChainError`, names the offending value
(file, element, argument, configuration) and, where there is a finite set of
valid choices, lists them. Every exception class is declared here, those the
compiled core raises included (src/cpp/expose-errors.cpp translates its C++
errors into them); :mod:`closedchain.simulate.settings` and
:mod:`closedchain.compiled` re-export the ones they used to declare.
"""

from __future__ import annotations

import math
import numbers
import reprlib
from collections.abc import Iterable

import numpy as np


class ClosedChainError(Exception):
    """Base class of every error raised by closedchain."""


class ModelFileError(ClosedChainError):
    """A model file is invalid: a URDF (or its URDF+ elements), SDF, MJCF or loops YAML file.

    The message names the file, the line or element, and the valid choices.
    """


#: Former name of :class:`ModelFileError` (the same class), kept for existing code.
URDFError = ModelFileError


class ModelTooLargeError(ModelFileError):
    """A tree has more degrees of freedom than closedchain supports (refused before any work).

    Attributes:
        nv: degrees of freedom of the tree.
        max_nv: the largest supported nv.
    """

    def __init__(self, message: str, *, nv: int, max_nv: int) -> None:
        super().__init__(message)
        self.nv = nv
        self.max_nv = max_nv


class LoopClosureError(ClosedChainError):
    """The frames of a loop joint cannot be brought together."""


class AssemblyError(ClosedChainError):
    """Newton / Levenberg-Marquardt assembly did not reach phi(q) = 0."""

    def __init__(self, message: str, residual: float, q) -> None:
        super().__init__(message)
        self.residual = residual
        self.q = q


class SingularConfigurationError(ClosedChainError):
    """A matrix a method must invert is singular or too ill-conditioned.

    Attributes:
        q: configuration at which it happened, shape (nq,).
        condition_number: estimated 2-norm or 1-norm condition number.
        t: simulation time [s] when raised during a simulation, else None.
        trajectory: when it stopped a simulation, the Trajectory recorded up to
            the stop (output samples before ``t``), else None.
    """

    def __init__(self, message: str, *, q=None, condition_number: float = float("inf"), t=None):
        super().__init__(message)
        self.q = q
        self.condition_number = condition_number
        self.t = t
        self.trajectory = None

    @classmethod
    def build(
        cls,
        name: str,
        what: str,
        *,
        q,
        cond: float,
        bound: float | None = None,
        bound_name: str = "cond_max",
        state: str = "is singular",
        detail: str = "",
        hint: str = "",
        t: float | None = None,
    ) -> SingularConfigurationError:
        """Return the error in the one message format every site uses.

        ``"{name}: [at t = {t} s ]{what} {state} at q = [...] (condition number
        {cond} > {bound_name} {bound}{detail}); {hint}"``; the comparison is
        written only when ``cond`` exceeds ``bound``.

        Args:
            name: mechanism name.
            what: the matrix or solver (``"the KKT matrix [[M, J^T], [J, 0]]"``).
            q: configuration, shape (nq,).
            cond: its condition number (inf when exactly singular).
            bound: the bound it was checked against, or None.
            bound_name: the setting holding ``bound``.
            state: what happened (``"is singular"``, ``"has lost rank"``).
            detail: appended inside the parentheses (start it with ``"; "``).
            hint: what to do, or what it means.
            t: simulation time [s], or None.
        """
        q = np.array(q, dtype=float)
        when = "" if t is None else f"at t = {t:.9g} s "
        if bound is None:
            versus = ""
        elif cond > bound:
            versus = f" > {bound_name} {bound:.1e}"
        else:
            versus = f", {bound_name} {bound:.1e}"
        message = (
            f"{name}: {when}{what} {state} at q = {_one_line(q)} "
            f"(condition number {cond:.3e}{versus}{detail})" + (f"; {hint}" if hint else "")
        )
        return cls(message, q=q, condition_number=cond, t=t)

    def with_hint(self, hint: str, *, t: float | None = None) -> SingularConfigurationError:
        """Return this error with ``"; {hint}"`` appended (and ``t`` [s] set when given)."""
        return type(self)(
            f"{self}; {hint}",
            q=self.q,
            condition_number=self.condition_number,
            t=self.t if t is None else t,
        )

    def at_time(self, t: float, *, hint: str = "") -> SingularConfigurationError:
        """Return this error with the simulation time ``t`` [s] prefixed and set.

        Args:
            t: simulation time [s].
            hint: appended after ``"; "`` when given (e.g. the configurations
                that pass singular positions).
        """
        return type(self)(
            f"at t = {t:.9g} s: {self}" + (f"; {hint}" if hint else ""),
            q=self.q,
            condition_number=self.condition_number,
            t=t,
        )


class SimulationError(ClosedChainError):
    """A simulation failed: non-finite state, integrator failure or drift beyond the limit.

    Attributes:
        t: simulation time [s] at which it happened.
        trajectory: the Trajectory recorded up to the stop (output samples
            before ``t``), or None.
    """

    def __init__(self, message: str, t: float) -> None:
        super().__init__(message)
        self.t = t
        self.trajectory = None


class BatchError(ClosedChainError):
    """Members of a :func:`closedchain.simulate_batch` failed (``BatchResult.check``).

    Attributes:
        failed: member index -> the exception that stopped it.
    """

    def __init__(self, message: str, *, failed: dict[int, Exception]) -> None:
        super().__init__(message)
        self.failed = failed


class RowCheckRequired(ClosedChainError):
    """Raised by a compiled loop when the kept rows stop describing the loops at ``t``.

    A dropped row opened (beyond ``SimulationSettings.dropped_row_tol`` and
    ``dropped_row_ratio`` times the kept rows' residual) or the kept rows
    degenerate where there are dropped rows: the rows must be re-selected
    (:meth:`LoopClosure.check_rows`), which the numpy backend does; the
    simulator then runs the request there (:mod:`closedchain.simulate.compiled_loops`).

    Attributes:
        t: simulation time [s] of the step that found it.
    """

    def __init__(self, message: str, t: float) -> None:
        super().__init__(message)
        self.t = t


class InvalidArgumentError(ClosedChainError, ValueError):
    """An argument is out of its valid range (the message names it and the range)."""


class NonFiniteError(ClosedChainError, ValueError):
    """A computation overflowed to inf or NaN (inputs too large for double precision)."""


#: Choices an UnknownChoiceError lists at most (the others are counted).
MAX_LISTED_CHOICES = 200


class UnknownChoiceError(ClosedChainError, ValueError):
    """An argument is not one of a fixed set of valid choices."""

    def __init__(self, what: str, value: object, choices: Iterable[str]) -> None:
        choices = sorted(choices)
        shown = ", ".join(shorten(c) for c in choices[:MAX_LISTED_CHOICES])
        if len(choices) > MAX_LISTED_CHOICES:
            shown += f", ... and {len(choices) - MAX_LISTED_CHOICES} more"
        name = quoted(value) if isinstance(value, str) else shorten(value)
        super().__init__(f"unknown {what} {name}; valid choices: {shown}")
        self.value = value
        self.choices = choices


class ValidationUnavailableError(ClosedChainError):
    """No equivalent Pinocchio constraint model exists for a loop type."""


def resolve_choice(what: str, value: object, choices: Iterable[str]) -> str:
    """Return the choice that ``value`` names, ignoring case, or raise listing the choices.

    Args:
        what: what is chosen, for the message (``"integrator"``).
        value: the name given.
        choices: the registered names (their own spelling is returned).

    Raises:
        UnknownChoiceError: no choice matches ``value`` case-insensitively.
    """
    choices = list(choices)
    if isinstance(value, str):
        if value in choices:
            return value
        folded = {c.casefold(): c for c in choices}
        match = folded.get(value.casefold())
        if match is not None:
            return match
    raise UnknownChoiceError(what, value, choices)


def format_upper_bound(x: float, digits: int = 6) -> str:
    """Return ``x`` with at least ``digits`` significant digits, never above ``x``.

    For "valid: (0, x]" messages: rounding to nearest could print a bound that
    is itself refused (1999999.8 as 2e+06); more digits are added until the
    printed number is at most ``x`` (17 always are).
    """
    for d in range(digits, 18):
        text = f"{x:.{d}g}"
        if not (math.isfinite(x) and float(text) > x):
            return text
    return repr(x)


#: Longest name or value [characters] quoted in a message; longer ones are cut in the
#: middle with "..." (a 60 MB frame name must not make a 60 MB message).
MESSAGE_NAME_MAX = 80
#: Longest message [characters] the command line prints (cut in the middle likewise).
MESSAGE_MAX = 2000


_BOUNDED_REPR = reprlib.Repr()  # Python 3.11: no keyword arguments
_BOUNDED_REPR.maxlevel = 3
_BOUNDED_REPR.maxstring = _BOUNDED_REPR.maxother = MESSAGE_NAME_MAX


def shorten(text: object, limit: int = MESSAGE_NAME_MAX) -> str:
    """Return ``text`` on one line, cut in the middle with ``"..."`` beyond ``limit``.

    Args:
        text: a name or message; anything else is shown by a bounded ``repr``.
        limit: the longest result [characters], at least 5.
    """
    if isinstance(text, str):
        s = text
    else:  # reprlib visits a bounded part of a nested value (YAML aliases share parts)
        s = _BOUNDED_REPR.repr(text)
    if len(s) > limit:
        head = (limit - 3 + 1) // 2
        s = s[:head] + "..." + s[len(s) - (limit - 3 - head) :]
    return " ".join(s.split()) if ("\n" in s or "\r" in s) else s


def quoted(name: str, limit: int = MESSAGE_NAME_MAX) -> str:
    """Return ``repr(name)`` (quotes, escapes: one line) cut as :func:`shorten` does."""
    return shorten(repr(name), limit)


def shown(value: object) -> str:
    """Return a value for a message: a string quoted (:func:`quoted`), anything else by a
    bounded ``repr`` (:func:`shorten`)."""
    return quoted(value) if isinstance(value, str) else shorten(value)


def _one_line(x) -> str:
    """Return the array ``x`` as numpy prints it (6 digits), on one line however long
    (a matrix's rows one after the other)."""
    import sys

    text = np.array2string(np.asarray(x, dtype=float), precision=6, max_line_width=sys.maxsize)
    return text.replace("\n", "")  # the rows of a matrix


def _is_number(value: object) -> bool:
    """Whether ``value`` is a real number (numpy's included), not a bool or a string."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)


def check_positive(name: str, value, what: str) -> float:
    """Return ``value`` as a float; raise InvalidArgumentError unless it is a finite number > 0.

    Args:
        name: argument name, for the message.
        value: the value given (a string, a bool or an array is refused).
        what: what the argument is, for the message.
    """
    x = float(value) if _is_number(value) else math.nan
    if not (math.isfinite(x) and x > 0):
        raise InvalidArgumentError(
            f"{name} ({what}) must be a finite number > 0, got {shown(value)}; "
            "valid range: (0, inf)"
        )
    return x


def check_count(name: str, value, what: str) -> int:
    """Return ``value`` as an int; raise InvalidArgumentError unless it is an integer >= 1.

    Args:
        name: argument name, for the message.
        value: the value given (2.5, True or "3" is refused).
        what: what the argument is, for the message.
    """
    if not (isinstance(value, numbers.Integral) and _is_number(value) and value >= 1):
        raise InvalidArgumentError(
            f"{name} ({what}) must be an integer >= 1, got {shorten(value)}; valid: 1, 2, 3, ..."
        )
    return int(value)


def check_settings(name: str, value: object, cls: type) -> None:
    """Raise InvalidArgumentError unless ``value`` is an instance of the settings class ``cls``.

    A settings object of another class (``simulate(settings=SolverSettings())``)
    would otherwise fail later with an AttributeError far from the mistake.

    Args:
        name: the argument's name, for the message.
        value: what was passed.
        cls: the settings class the argument takes.
    """
    if not isinstance(value, cls):
        raise InvalidArgumentError(
            f"{name} must be a {cls.__name__} (from {cls.__module__}), got a {type(value).__name__}"
        )
