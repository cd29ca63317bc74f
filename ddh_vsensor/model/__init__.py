"""The DDH unit's dynamics, defined once: one backward-Euler step in C (``_unit.c``), run
over batches of units by the simulator's plant and, next, by the estimator's filter."""
