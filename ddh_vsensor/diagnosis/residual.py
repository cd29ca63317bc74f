"""The data-driven residual model: what the error follows when no catalogue cause explains it.

The velocity error is modelled as a linear combination of physical features of the inputs
(:func:`estimator.extension.residual_features`: estimated velocity, torque over viscosity,
torque, speed, speed cubed, velocity x |torque|, torque beyond three knots on either side, a constant). Integrated over
each run, they are fitted to the position error by ridge regression with the ridge weight
chosen by leave-one-run-out cross-validation; the model is linear in its weights and its
features do not depend on them, so the held-out error is exact. The weights are on
standardised features, so their sizes say which signal the error follows.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.estimator.extension import (RESIDUAL_FEATURES, ResidualModel, corrected_inputs,
                                   integrate_rate, residual_features)
from ddh_vsensor.diagnosis.workbench import Workbench

ALPHAS = (1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1)
KNOT_QUANTILES = (0.25, 0.5, 0.75)


@dataclass
class ResidualFit:
    model: ResidualModel
    heldout: list[np.ndarray]               # residual (mm) of held-out run j
    explained: float                        # share of the baseline's held-out SSE removed
    alpha: float

    def follows(self) -> list[tuple[str, float]]:
        """Features by the share of the fitted correction they carry, largest first."""
        w = np.abs(np.asarray(self.model.weights))
        share = w / w.sum() if w.sum() > 0 else w
        return sorted(zip(RESIDUAL_FEATURES, map(float, share)), key=lambda x: -x[1])


def features(bench: Workbench, params: Mapping[str, float], knots: tuple[float, ...]
             ) -> tuple[list[np.ndarray], np.ndarray]:
    """Integrated features per run (masked samples) under the extended model ``params``, and
    each feature's RMS over all samples (its scale)."""
    out, squares, count = [], np.zeros(len(RESIDUAL_FEATURES)), 0
    gap = bench.cfg.estimator.max_gap_s
    for r, m in zip(bench.runs, bench.masks):
        n, pumps, tau, temp = corrected_inputs(params, r.time_s, r.speed_rpm, r.torque_nm,
                                               r.oil_temp_c)
        est = Estimator(bench.estimator_config, bench.actuator, bench.scaled_tables(params),
                        mode=bench.mode, references=False, adaptation=False,
                        initial_position_mm=r.initial_position_mm
                        / params.get("position_scale", 1.0))
        v = est.run(r.time_s, pumps, tau, temp).velocity_mm_s
        f = residual_features(n, tau, bench.unit.oil.dynamic_viscosity_pa_s(temp), v, knots)
        squares += np.sum(f ** 2, axis=0)
        count += len(f)
        out.append(np.stack([integrate_rate(r.time_s, f[:, i], gap)
                             for i in range(f.shape[1])], axis=1)[m])
    rms = np.sqrt(squares / max(count, 1))
    return out, np.where(rms > 0.0, rms, 1.0)


def fit_residual(bench: Workbench, params: Mapping[str, float], target: Sequence[np.ndarray],
                 weights: Sequence[float], total: float) -> ResidualFit:
    """Fit the residual model to ``target`` (per run, masked: the error left by the extended
    model ``params``, as held out) and cross-validate it."""
    tau_all = np.concatenate([np.abs(r.torque_nm) for r in bench.runs])
    knots = tuple(float(np.quantile(tau_all, q)) for q in KNOT_QUANTILES)
    raw, scale = features(bench, params, knots)                # type: ignore[arg-type]
    x = [f / scale for f in raw]
    a_j = [w * xx.T @ xx for xx, w in zip(x, weights)]
    b_j = [w * xx.T @ yy for xx, yy, w in zip(x, target, weights)]
    a_all, b_all = sum(a_j), sum(b_j)
    p = a_all.shape[0]
    eye = np.eye(p)
    best = None
    for alpha in ALPHAS:
        lam = alpha * np.trace(a_all) / p
        held = []
        for j in range(len(x)):
            wj = np.linalg.solve(a_all - a_j[j] + lam * eye, b_all - b_j[j])
            held.append(target[j] - x[j] @ wj)
        sse = float(sum(w * np.dot(h, h) for h, w in zip(held, weights)))
        if best is None or sse < best[0]:
            best = (sse, alpha, held, lam)
    sse, alpha, held, lam = best
    w_all = np.linalg.solve(a_all + lam * eye, b_all)
    model = ResidualModel(tuple(map(float, w_all)), tuple(map(float, scale)), knots)
    return ResidualFit(model, held, 1.0 - sse / total if total > 0 else 0.0, alpha)
