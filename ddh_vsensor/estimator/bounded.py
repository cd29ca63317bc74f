"""Integration between soft limits, vectorised.

Sequentially, x[k] = clip(x[k-1] + dx[k], lower, upper). While pinned at one limit this is a
one-sided reflection with a closed form (x = limit + C - running extreme of C), so a whole
run is a handful of numpy passes: one per time the estimate runs from one limit to the other.
"""

from __future__ import annotations

import numpy as np


def bounded_cumsum(x_start: float, dx: np.ndarray, lower: float,
                   upper: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions after each increment, and where a limit acted (equal to the clipped loop)."""
    n = len(dx)
    x = np.empty(n)
    i, start = 0, x_start
    while i < n:
        # added in the loop's order (start + dx0) + dx1 ..., not start + (dx0 + dx1 ...):
        # equal to the online step's sums to the bit, which the chamber model's decisions
        # (fed the position at each reference) can turn on
        y = np.add.accumulate(np.concatenate([[start], dx[i:]]))[1:]
        out = (y > upper) | (y < lower)
        if not out.any():
            x[i:] = y
            break
        j = i + int(np.argmax(out))
        x[i:j] = y[:j - i]
        limit, sign = (upper, 1.0) if y[j - i] > upper else (lower, -1.0)
        # Pinned from j on: x = limit + C - extreme(C), C the sum of increments after j.
        c = np.concatenate([[0.0], np.cumsum(dx[j + 1:])])
        pinned = limit + (c - sign * np.maximum.accumulate(sign * c))
        escape = (pinned < lower) if sign > 0 else (pinned > upper)
        end = j + (int(np.argmax(escape)) if escape.any() else len(c))
        x[j:end] = pinned[:end - j]
        if end == n:
            break
        i, start = end, x[end - 1]
    return x, (x <= lower) | (x >= upper)
