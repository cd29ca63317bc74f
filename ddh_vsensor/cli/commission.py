"""``ddh-vsensor commission``: a machine's Hall switches and its pumps' flow model measured on
its calibration runs (the draw-wire position still fitted), written into its configuration,
and the machine's baseline (the commissioned model's own error on runs held out of the fit)
beside it."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ddh_vsensor.atomic import output_dir, output_file
from ddh_vsensor.cli.progress import ProgressBar
from ddh_vsensor.commission.baseline import KINDS as BASELINE_KINDS
from ddh_vsensor.commission.baseline import Baseline
from ddh_vsensor.commission.drive import DriveFit
from ddh_vsensor.commission.flow import FlowFit
from ddh_vsensor.commission.switches import (KIND_WORDS, KINDS, SPREAD_FACTOR, UnitCalibration,
                                             calibrate_unit)
from ddh_vsensor.config import Config, load_config
from ddh_vsensor.errors import UserError
from ddh_vsensor.io.csv import header_actuator, read_csv
from ddh_vsensor.measured import Run


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "commission", help="measure the Hall switches' switching points and the pumps' "
                           "leakage on calibration runs with the position sensor fitted; "
                           "write the machine's configuration",
        description="Finds every Hall switch's edges in the runs, the rod's measured position "
                    "at each, and fits the configuration's switch positions, window and "
                    "hysteresis to them; the tolerance becomes the fit's largest residual plus "
                    "k x the edges' spread. Fits each unit's pump leakage and displacement "
                    "(per side), the leakage's orifice share and speed gain (and, from logged "
                    "chamber pressures, the oil's entrained air and the hoses' expansion) to "
                    "the chambers' oil balance against the measured travel. Writes the "
                    "datasheet configuration with those keys set and commented with their "
                    "evidence; a value the runs do not measure keeps the "
                    "datasheet's, with the run that would measure it. Writes the machine's "
                    "baseline beside it: the commissioned model's own error on each run file "
                    "when commissioned on the others, per unit, for 'analyze --baseline'.")
    p.add_argument("runs", nargs="+", metavar="RUN",
                   help="calibration runs: CSV of the measured-data format with position_mm "
                        "(one unit each, its '# actuator:' line or --actuator), or CAN logs "
                        "with the draw-wire frames (every unit, or --actuator's)")
    p.add_argument("--config", metavar="FILE", required=True,
                   help="the datasheet configuration the machine was filled in with")
    p.add_argument("--out", metavar="FILE.yaml", required=True,
                   help="the commissioned configuration (the datasheet file with the "
                        "measured keys set; not the datasheet itself)")
    p.add_argument("--actuator", metavar="UNIT", default=None,
                   help="commission this unit only (default: every unit the runs hold)")
    p.add_argument("--report", metavar="DIR",
                   help="write commission.json (every edge per switch, each kind's "
                        "statistics, each unit's flow fit) and commission.html")
    p.add_argument("--switches-only", action="store_true",
                   help="calibrate the Hall switches only, not the pumps' flow model")
    p.add_argument("--spread-factor", type=float, default=SPREAD_FACTOR, metavar="K",
                   help="the tolerance is the largest residual plus K standard deviations of "
                        "the edges (default %(default)g)")
    p.add_argument("--baseline", metavar="FILE.json", default=None,
                   help="the machine's baseline (default: beside --out, "
                        "MACHINE.baseline.json); needs at least two run files")
    p.add_argument("--no-baseline", action="store_true",
                   help="do not measure the baseline (it commissions once more per run file)")
    p.set_defaults(func=_run)


def _has_position(run: Run) -> bool:
    return bool(np.isfinite(run.position_mm).any())


def read_runs(paths: list[str], cfg: Config, actuator: str | None) -> dict[str, list[Run]]:
    """The runs per unit; a CSV is one unit's, a CAN log every unit's (those with position)."""
    from ddh_vsensor.io.log import read_can_log
    runs: dict[str, list[Run]] = {a: [] for a in ([actuator] if actuator else cfg.unit_names)}
    bar = ProgressBar("commission")
    for i, path in enumerate(paths):
        bar.update(i / len(paths), Path(path).name)
        if path.lower().endswith(".csv"):
            run = read_csv(path, require_position=True, actuator=actuator)
            unit = actuator or header_actuator(run.comments)
            if unit is None:
                if len(cfg.unit_names) != 1:
                    raise UserError(f"{path}: no '# actuator:' line: say which unit it is "
                                    f"(--actuator; units: {', '.join(cfg.unit_names)})")
                unit = cfg.unit_names[0]
            runs[cfg.require_unit(unit)].append(run)
            continue
        found = False
        for unit, unit_runs in runs.items():
            run = read_can_log(path, unit, cfg)
            if _has_position(run):
                unit_runs.append(run)
                found = True
        if not found:
            raise UserError(f"{path}: no draw-wire position of "
                            f"{'the ' + actuator if actuator else 'any unit'}: commissioning "
                            f"needs the position sensor fitted")
    bar.close(f"{len(paths)} runs read")
    return {a: r for a, r in runs.items() if r}


def _summary(cal: UnitCalibration) -> list[str]:
    lines = []
    for s in cal.switches.values():
        if not s.calibrated:
            lines.append(f"  {s.name}: not calibrated: {s.problem}")
            continue
        seen = ", ".join(f"{KIND_WORDS[k]} {s.kinds[k].mean_mm:.2f}" for k in KINDS
                         if s.kinds[k].count)
        lines.append(f"  {s.name}: {s.position_mm:.2f} mm (datasheet {s.configured_mm:g}) "
                     f"+-{s.tolerance_mm:.2f}, {len(s.edges)} edges: {seen} mm")
    lines.append(f"  window {cal.window_mm:.2f} mm (datasheet {cal.configured_window_mm:g}), "
                 f"hysteresis {cal.hysteresis_mm:.2f} mm ({cal.configured_hysteresis_mm:g}), "
                 f"tolerance {cal.tolerance_mm:.2f} mm ({cal.configured_tolerance_mm:g})")
    lines += [f"  {note}" for note in cal.notes]
    return lines


def _drive_summary(fit: DriveFit) -> str:
    if not fit.measured:
        return f"drive's torque reading not measured: {fit.why_not}"
    gain = (f"gain 1 (not measured: {fit.gain_why_not})" if fit.gain_why_not else
            f"gain {fit.gain:.4f} +- {fit.gain_sigma:.4f}")
    return (f"drive's torque reading: {gain}, offset {fit.offset_nm:+.2f} +- "
            f"{fit.offset_sigma_nm:.2f} N*m, {fit.speed_offset_nm:+.2f} N*m more at the speed "
            f"limit, filter {fit.filter_s * 1e3:.1f} ms")


def _flow_summary(fit: FlowFit) -> list[str]:
    lines = [f"  flow model (pressures {fit.pressures}; windows A {fit.windows['a']}, "
             f"B {fit.windows['b']}; loaded A {fit.loaded_windows['a']}, "
             f"B {fit.loaded_windows['b']}):"]
    for name, e in fit.named():
        lines.append(f"    {name}: " + (f"{e.value:.3f} +-{e.sd:.3f}" if e.identified
                                         else f"not measured ({e.problem})"))
    for s, rms in fit.residual_rms_ml.items():
        lines.append(f"    side {s.upper()}: balance residual {rms:.2f} ml per window "
                     f"(datasheet model {fit.datasheet_rms_ml[s]:.2f})")
    return lines


def fit_machine(cfg: Config, runs: dict[str, list[Run]], spread_factor: float,
                switches_only: bool
                ) -> tuple[dict[str, UnitCalibration], dict[str, FlowFit], dict[str, str],
                           dict[str, DriveFit]]:
    """Each unit's switches, flow model and drive reading from its runs: (calibrations, flow
    fits, why a unit's flow model was not measured, drive fits)."""
    from ddh_vsensor.commission.drive import fit_drive
    from ddh_vsensor.commission.flow import applied, fit_flows
    cals = {a: calibrate_unit(a, cfg.unit(a), r, cfg.estimator.debounce_s, spread_factor)
            for a, r in runs.items()}
    flows: dict[str, FlowFit] = {}
    flow_problems: dict[str, str] = {}
    drives: dict[str, DriveFit] = {}
    if not switches_only:
        for a, unit_runs in runs.items():
            try:
                flows.update(fit_flows(cfg, {a: unit_runs}))
            except UserError as exc:
                flow_problems[a] = str(exc)
            # the pressures' torque through the pumps as commissioned: the drive's gain is
            # relative to the displacement the calibrated configuration carries
            drives[a] = fit_drive(applied(cfg, flows), a, unit_runs)
    return cals, flows, flow_problems, drives


def _baseline_path(args: argparse.Namespace, out: Path) -> Path | None:
    """Where the baseline goes (checked before the work), None with --no-baseline."""
    if args.no_baseline:
        if args.baseline is not None:
            raise UserError("--baseline and --no-baseline: give one")
        return None
    return output_file(args.baseline or out.with_name(f"{out.stem}.baseline.json"),
                       "baseline", (".json",))


def _measure_baseline(cfg: Config, machine: Config, text: str, source: str,
                      runs: dict[str, list[Run]], args: argparse.Namespace) -> Baseline:
    """Leave one run file out at a time: commission on the others, score the one left out."""
    from ddh_vsensor.commission.baseline import LEAVE_ONE_OUT, leave_one_out, measure
    from ddh_vsensor.commission.machine import commissioned_config
    from ddh_vsensor.diagnosis.workbench import resolve_mode

    def fit(rest: dict[str, list[Run]]) -> Config:
        cals, flows, _, drives = fit_machine(cfg, rest, args.spread_factor,
                                             args.switches_only)
        return commissioned_config(text, source, cals, args.spread_factor, flows, cfg, drives)

    names = list(dict.fromkeys(r.source for rs in runs.values() for r in rs))
    bar = ProgressBar("baseline")
    done = [0]

    def progress(what: str) -> None:
        """One call per run file held out (after its fold's fit)."""
        bar.update(done[0] / len(names), what)
        done[0] += 1

    base = measure(leave_one_out(runs, fit), machine.estimate_hash(), LEAVE_ONE_OUT, names,
                   resolve_mode(machine, None), progress=progress)
    bar.close(f"{len(names)} run files held out")
    return base


def _baseline_summary(base: Baseline) -> list[str]:
    lines = [f"baseline ({base.mode} mode, each run file held out):"]
    for unit, b in base.units.items():
        kinds = ", ".join(f"{k} {b.kinds[k].rms_mm:.2f} mm RMS (p95 {b.kinds[k].p95_mm:.2f}, "
                          f"{b.kinds[k].count})" for k in BASELINE_KINDS if k in b.kinds)
        line = b.pressures
        if line is not None:
            kinds += (f", pressures' line {line.gain:.3f} x {line.offset_nm:+.2f} N*m "
                      f"(sd {100 * line.gain_sd:.1f} %, {line.offset_sd_nm:.2f} N*m)")
        lines.append(f"  {unit}: {kinds or 'nothing held out'}")
    return lines


def _run(args: argparse.Namespace) -> int:
    from ddh_vsensor.commission.machine import read_datasheet, write_config, write_report
    if not (args.spread_factor >= 0.0 and np.isfinite(args.spread_factor)):
        raise UserError(f"--spread-factor must be a number >= 0, got {args.spread_factor:g}")
    datasheet, out = Path(args.config), output_file(args.out, "commissioned configuration",
                                                    (".yaml", ".yml"))
    if out.exists() and datasheet.exists() and out.samefile(datasheet):
        raise UserError(f"{out}: the datasheet configuration itself: write the machine's "
                        "configuration beside it")
    baseline = _baseline_path(args, out)
    files = len(dict.fromkeys(args.runs))
    if baseline is not None and files < 2 and args.baseline is not None:
        raise UserError(f"{baseline}: a baseline needs at least two run files (each is held "
                        f"out of the fit in turn), {files} given")
    report = output_dir(args.report, "report directory", create=False) if args.report else None
    cfg = load_config(datasheet)
    if args.actuator is not None:
        cfg.require_unit(args.actuator)
    runs = read_runs(args.runs, cfg, args.actuator)
    cals, flows, flow_problems, drives = fit_machine(cfg, runs, args.spread_factor,
                                                     args.switches_only)
    if not any(c.calibrated for c in cals.values()) and not any(
            f.measured for f in flows.values()):
        problems = [p for c in cals.values() for p in c.problems]
        raise UserError("no switch calibrated and no flow value measured: " + (
            "; ".join(problems) or "the runs hold no unit with its position"))
    machine = write_config(datasheet, out, cals, args.spread_factor, flows, cfg, drives)
    for a, cal in cals.items():
        print(f"{a}: {len(runs[a])} runs, {len(cal.calibrated)} of {len(cal.switches)} "
              "switches calibrated")
        print("\n".join(_summary(cal)))
        if a in flows:
            print("\n".join(_flow_summary(flows[a])))
        elif a in flow_problems:
            print(f"  flow model not measured: {flow_problems[a]}")
        if a in drives:
            print(f"  {_drive_summary(drives[a])}")
    missing = [a for a in cfg.unit_names if a not in cals and args.actuator is None]
    if missing:
        print(f"not commissioned (no run with its position): {', '.join(missing)}")
    print(f"written: {out}")
    if baseline is not None and files < 2:
        print("baseline not written: one run file (each is held out of the fit in turn: "
              "give at least two)")
    elif baseline is not None:
        base = _measure_baseline(cfg, machine, read_datasheet(datasheet), str(datasheet),
                                 runs, args)
        print("\n".join(_baseline_summary(base)))
        print(f"written: {base.save(baseline)}")
    if report is not None:
        print(f"report: {write_report(output_dir(report, 'report directory'), cals, flows)}")
    return 0
