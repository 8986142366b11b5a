"""Backtracking (Armijo) line search."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Generic, TypeVar

import numpy as np

__all__ = ["armijo_backtracking", "LineSearchResult"]

S = TypeVar("S")


@dataclass
class LineSearchResult(Generic[S]):
    """Outcome of :func:`armijo_backtracking`.

    Attributes
    ----------
    accepted : bool
        Whether a step with sufficient decrease was found.
    step : float
        The accepted step length (the last one tried when not accepted).
    value : float
        Objective at the accepted step (``inf`` when none was accepted).
    state : object
        Whatever ``evaluate`` returned with the accepted value (e.g. its gradient).
    trials : int
        Number of objective evaluations spent.
    """

    accepted: bool
    step: float
    value: float
    state: S | None
    trials: int


def armijo_backtracking(
    evaluate: Callable[[float], tuple[float, S]],
    value0: float,
    slope: float,
    step: float,
    c: float = 1e-4,
    shrink: float = 0.5,
    max_trials: int = 20,
) -> LineSearchResult[S]:
    """Shrink ``step`` until ``phi(step) <= phi(0) + c * step * phi'(0)``.

    A trial whose value is NaN or infinite is never accepted.

    Parameters
    ----------
    evaluate : callable
        ``step -> (phi(step), state)``.
    value0 : float
        ``phi(0)``.
    slope : float
        ``phi'(0)``, negative for a descent direction.
    step : float
        First trial step.
    c, shrink : float
        Sufficient-decrease constant and shrink factor.
    max_trials : int

    Examples
    --------
    >>> r = armijo_backtracking(lambda a: ((1 - a) ** 2, None), 1.0, -2.0, step=4.0)
    >>> r.accepted, r.step
    (True, 1.0)
    """
    for trial in range(1, max_trials + 1):
        value, state = evaluate(step)
        if np.isfinite(value) and value <= value0 + c * step * slope:
            return LineSearchResult(True, step, float(value), state, trial)
        if trial < max_trials:
            step *= shrink
    return LineSearchResult(False, step, float("inf"), None, max_trials)
