"""The DDH unit's dynamics, defined once: one backward-Euler step in C (``_unit.c``, bound in
:mod:`.unit`), and :class:`.plant.Plant`, a batch of units stepped in lockstep, which the
simulator drives (adding the controller and the load cycle) and the estimator's filter is
built on."""
