"""The motor's own inertia: whether the estimator takes it off the motor torque.

The movement tables map *pump* torque (at the motor shaft) to motion; the drive reports the
*motor* torque, which also accelerates the rotor and the pumps: tau_pump = tau - J d(omega)/dt.
The estimator does this itself (``estimator.inertia_compensation``); diagnosis evaluates every
cause with and without it and keeps the better, recorded in the extension as ``motor_inertia``.
"""

from __future__ import annotations

import dataclasses

from ..config import Config


def with_inertia_compensation(cfg: Config, on: bool) -> Config:
    """``cfg`` with the estimator's inertia compensation switched on or off."""
    if cfg.estimator.inertia_compensation == on:
        return cfg
    return dataclasses.replace(cfg, estimator=dataclasses.replace(cfg.estimator,
                                                                  inertia_compensation=on))
