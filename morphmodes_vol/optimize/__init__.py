"""Stage 3, optimize: Algorithm 1 (adaptive subspace gradient descent) and its line search."""

from .adaptive import (AdaptiveResult, AdaptiveRun, OptimizationHistory, ProgressEvent, optimize_adaptive,
                       single_threaded_blas)
from .linesearch import LineSearchResult, armijo_backtracking

__all__ = [
    "optimize_adaptive",
    "AdaptiveRun",
    "single_threaded_blas",
    "AdaptiveResult",
    "OptimizationHistory",
    "ProgressEvent",
    "armijo_backtracking",
    "LineSearchResult",
]
