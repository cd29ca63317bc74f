"""Benchmark: offline estimator samples per second and the online step's cost, both units,
in the table mode (`full`) and the chamber-model mode (`dynamic`), and the same for the
Kalman filter (`kalman`: :mod:`ddh_vsensor.estimator.kalman`): its offline face
(``run_many``) on one run alone, on the first ``KALMAN_OFFLINE`` samples, and its online face
(``OnlineKalman.update``) sample by sample, the first sample (which builds the filter) not
timed, and again with entrained air configured (``hydraulics.air_fraction``, as commissioning
writes it where the pressures were logged: the mixture law's compression is iterated in every
row's step). The signals are no plant's: the filter finds them inconsistent with its model and
widens; its cost per sample is the same either way."""

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
from ddh_vsensor.tables.build import build_unit_tables  # noqa: E402

KALMAN_OFFLINE = 200_000        # samples of the filter's offline run (some 8 us each)
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


def _run(signals: tuple[np.ndarray, ...], count: int) -> Run:
    """The signals' first ``count`` samples as a log (no position measured)."""
    t, speed, torque, temp, mid = (a[:count] for a in signals)
    return Run(t, speed, torque, temp, np.full(count, np.nan),
               refs={"mid": mid.astype(np.int8)}, source="<bench>")


def main() -> None:
    cfg = load_config(None)
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
        signals = (t, n, q, temp, mid)
        kalman.run_many(cfg, [(actuator, _run(signals, 1000))], initial_positions_mm=[100.0])
        n_off = KALMAN_OFFLINE
        run = _run(signals, n_off)
        t0 = time.perf_counter()
        kalman.run_many(cfg, [(actuator, run)], initial_positions_mm=[100.0])
        figures[f"kalman_{actuator}_offline_samples_per_s"] = round(
            n_off / (time.perf_counter() - t0))
        # online: sample by sample, as a service feeds it, without air and with
        airy = dataclasses.replace(cfg, hydraulics=dataclasses.replace(
            cfg.hydraulics, air_fraction=AIR_FRACTION))
        for key, config in (("online_step_us", cfg), ("online_step_us_with_air", airy)):
            online = kalman_online.OnlineKalman(config, actuator, float(t[1] - t[0]),
                                                initial_position_mm=100.0)
            update = online.update
            update(*args[0], ref_dicts[0])
            rest = list(zip(args[1:], ref_dicts[1:]))
            t0 = time.perf_counter()
            for (tk, nk, qk, tc), r in rest:
                update(tk, nk, qk, tc, r)
            figures[f"kalman_{actuator}_{key}"] = round(
                (time.perf_counter() - t0) / (count - 1) * 1e6, 2)
        print(f"{'kalman':8} {actuator:7} offline "
              f"{figures[f'kalman_{actuator}_offline_samples_per_s']} samples/s, online "
              f"{figures[f'kalman_{actuator}_online_step_us']} us/step, with "
              f"{AIR_FRACTION:.1%} air {figures[f'kalman_{actuator}_online_step_us_with_air']} "
              "us/step", flush=True)
    figures["goal_offline_Msamples_s"] = 2.0
    figures["goal_online_step_us"] = 20.0
    publish("estimator", figures)


if __name__ == "__main__":
    main()
