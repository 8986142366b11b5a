"""Stage 3, optimize: Algorithm 1 (adaptive subspace gradient descent) and its line search."""

from .adaptive import AdaptiveResult, OptimizationHistory, ProgressEvent, optimize_adaptive
from .linesearch import LineSearchResult, armijo_backtracking

__all__ = [
    "optimize_adaptive",
    "AdaptiveResult",
    "OptimizationHistory",
    "ProgressEvent",
    "armijo_backtracking",
    "LineSearchResult",
]
