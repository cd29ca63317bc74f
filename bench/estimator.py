"""Benchmark: offline estimator samples per second and the online step's cost, both units,
in the table mode (`full`) and the chamber-model mode (`dynamic`), and the same for the
Kalman filter (`kalman`: :mod:`ddh_vsensor.estimator.kalman`): its offline face
(``run_many``) on one run alone, on the first ``KALMAN_OFFLINE`` samples, and its online face
(``OnlineKalman.update``) sample by sample, the first sample (which builds the filter) not
timed, and again with entrained air configured (``hydraulics.air_fraction``, as commissioning
writes it where the pressures were logged: the mixture law's compression is iterated in every
row's step). The table and chamber modes take a synthetic signal; the filter takes the
simulator's paper cycle at the drive's 100 Hz, once on the configured plant and once with the
air in it too: on a signal no unit could produce the filter's state leaves the physical range
and its cost follows where it ends up (the air law's iterations), so it is timed following a
plant."""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import publish  # noqa: E402

from ddh_vsensor.config import load_config  # noqa: E402
from ddh_vsensor.estimator import kalman, kalman_online  # noqa: E402
from ddh_vsensor.estimator.estimator import Estimator  # noqa: E402
from ddh_vsensor.measured import Run  # noqa: E402
from ddh_vsensor.sim.run import RunSpec, simulate  # noqa: E402
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402

KALMAN_CYCLES = 80              # paper cycles of the filter's timed run (~200 k samples)
KALMAN_ONLINE = 20_000          # of them, the samples the online face is timed over
AIR_FRACTION = 0.005            # entrained air of the online filter's second timing


def _signals(count: int, seed: int) -> tuple[np.ndarray, ...]:
    """A smooth work-cycle-like signal at 1 kHz with a mid reference switch toggling."""
    rng = np.random.default_rng(seed)
    t = np.arange(count) * 1e-3
    speed = 4000 * np.sin(2 * np.pi * t / 8.0) + rng.normal(0, 5, count)
    torque = 20 + 5 * np.sin(2 * np.pi * t / 3.0)
    temp = np.round(27 + 0.001 * t, 1)          # the bus's resolution (OilTemp, 0.1 degC)
    mid = (np.sin(2 * np.pi * t / 8.0) > 0.95)
    return t, speed, torque, temp, mid


def _work(cfg) -> dict[str, Run]:
    """The paper cycle :data:`KALMAN_CYCLES` times over (500 kg, 40 degC): a plant's signals."""
    return simulate(cfg, RunSpec(cycle="paper", speed=4, payload_kg=500.0, oil_temp_c=40.0,
                                 cycles=KALMAN_CYCLES))


def main() -> None:
    cfg = load_config(None)
    airy = dataclasses.replace(cfg, hydraulics=dataclasses.replace(
        cfg.hydraulics, air_fraction=AIR_FRACTION))
    work = {"online_step_us": (cfg, _work(cfg)), "online_step_us_with_air": (airy, _work(airy))}
    figures: dict[str, object] = {}
    for actuator in cfg.unit_names:
        tables = build_unit_tables(cfg, actuator)
        t, n, q, temp, mid = _signals(2_000_000, 0)
        refs = {"mid": mid}
        # the online faces' inputs, as a service hands them over: Python floats and dicts
        count = 100_000
        args = list(zip(t[:count].tolist(), n[:count].tolist(), q[:count].tolist(),
                        temp[:count].tolist()))
        ref_dicts = [{"mid": bool(m)} for m in mid[:count]]
        for mode in ("full", "dynamic"):
            est = Estimator(cfg, actuator, tables, mode=mode, initial_position_mm=100.0)
            t0 = time.perf_counter()
            est.run(t, n, q, temp, refs)
            figures[f"{mode}_{actuator}_offline_Msamples_s"] = round(
                len(t) / (time.perf_counter() - t0) / 1e6, 2)
            est = Estimator(cfg, actuator, tables, mode=mode, initial_position_mm=100.0)
            step = est.step
            t0 = time.perf_counter()
            for (tk, nk, qk, tc), r in zip(args, ref_dicts):
                step(tk, nk, qk, tc, r)
            figures[f"{mode}_{actuator}_online_step_us"] = round(
                (time.perf_counter() - t0) / count * 1e6, 2)
            print(f"{mode:8} {actuator:7} offline "
                  f"{figures[f'{mode}_{actuator}_offline_Msamples_s']} M samples/s, online "
                  f"{figures[f'{mode}_{actuator}_online_step_us']} us/step", flush=True)
        # the Kalman filter: offline on one run alone (no batch to share the plant's calls),
        # after a short run untimed (a process computes the filter's CUSUM threshold once)
        run = work["online_step_us"][1][actuator]
        x0 = [float(run.position_mm[0])]
        kalman.run_many(cfg, [(actuator, run.head(1000))], initial_positions_mm=x0)
        t0 = time.perf_counter()
        kalman.run_many(cfg, [(actuator, run)], initial_positions_mm=x0)
        figures[f"kalman_{actuator}_offline_samples_per_s"] = round(
            len(run.time_s) / (time.perf_counter() - t0))
        # online: sample by sample, as a service feeds it, without air and with
        for key, (config, runs) in work.items():
            r = runs[actuator].head(KALMAN_ONLINE)
            inputs = list(zip(r.time_s.tolist(), r.speed_rpm.tolist(), r.torque_nm.tolist(),
                              r.oil_temp_c.tolist(),
                              ({name: bool(v[k]) for name, v in r.refs.items()}
                               for k in range(len(r.time_s)))))
            online = kalman_online.OnlineKalman(config, actuator, float(r.time_s[1] - r.time_s[0]),
                                                initial_position_mm=float(r.position_mm[0]))
            update = online.update
            update(*inputs[0])
            t0 = time.perf_counter()
            for tk, nk, qk, tc, refs_k in inputs[1:]:
                update(tk, nk, qk, tc, refs_k)
            figures[f"kalman_{actuator}_{key}"] = round(
                (time.perf_counter() - t0) / (len(inputs) - 1) * 1e6, 2)
        print(f"{'kalman':8} {actuator:7} offline "
              f"{figures[f'kalman_{actuator}_offline_samples_per_s']} samples/s, online "
              f"{figures[f'kalman_{actuator}_online_step_us']} us/step, with "
              f"{AIR_FRACTION:.1%} air {figures[f'kalman_{actuator}_online_step_us_with_air']} "
              "us/step", flush=True)
    figures["goal_offline_Msamples_s"] = 2.0            # the table and chamber-model modes
    figures["goal_online_step_us"] = 20.0
    figures["goal_kalman_offline_samples_per_s"] = 1_000_000
    figures["goal_kalman_online_step_us"] = 10.0
    publish("estimator", figures)


if __name__ == "__main__":
    main()
