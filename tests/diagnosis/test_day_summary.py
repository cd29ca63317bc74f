"""The daemon's day summary: a day's stretches add up to what the fleet analysis finds in a
log of them, whatever the blocks the samples come in, across restarts, gaps and midnight;
written periodically and small; a corrupt file refused in one line."""

from __future__ import annotations

import dataclasses
import gzip
import json
from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.diagnosis import day_summary as ds
from ddh_vsensor.diagnosis.evidence import fit_log
from ddh_vsensor.diagnosis.references import reference_run
from ddh_vsensor.estimator.day_samples import SampleFeed, run_samples
from ddh_vsensor.measured import Run

from .conftest import FLEET_DAY

DAY0 = FLEET_DAY


@pytest.fixture(scope="module")
def sessions(fleet_sessions) -> list[dict[str, Run]]:
    return fleet_sessions


def summarise(cfg, runs, directory: Path | None = None, block_s: float | None = None,
              days: ds.DaySummaries | None = None, close: bool = True) -> ds.DaySummaries:
    """The runs through the daemon's feeds, in blocks of ``block_s`` (None: a run each)."""
    days = days or ds.DaySummaries(cfg, "M1", directory, lean=False, resume=False)
    feeds = {a: SampleFeed(list(cfg.unit(a).references_mm)) for a in cfg.can.units}
    for per_unit in runs:
        for actuator, run in per_unit.items():
            feed = feeds[actuator]
            for t, n, q, c, h, e in run_samples(feed.switches, run):
                feed.add_bits(t, n, q, c, h, e, t)
                if block_s is not None and feed.pending_s() >= block_s:
                    days.feed(actuator, feed.take())
            days.feed(actuator, feed.take())
    if close:
        days.close()
    return days


def same(units: dict, expected: dict) -> None:
    """Equal units' evidence (the context's means to rounding: sums in another order)."""
    assert units.keys() == expected.keys()
    for a, u in expected.items():
        for k, v in u.items():
            if isinstance(v, dict) and "mean" in v:
                assert units[a][k] == {**v, "mean": pytest.approx(v["mean"], rel=1e-12)}
            else:
                assert units[a][k] == v, (a, k)


def doc(days: ds.DaySummaries, day: str = "2026-03-02") -> dict:
    return days.document(days.days[day]) if day in days.days else \
        json.loads(days.path(day).read_text())


def test_a_day_counts_every_observation_once_as_the_log_analysis_does(cfg, sessions, tmp_path):
    """One session cut into stretches: the increments and holds of the whole run, each
    once; each cause's loss within a few % of the whole run's (the estimator restarts at
    the edge a stretch starts at), its best grid value the same."""
    days = summarise(cfg, sessions[:1], tmp_path)
    d = json.loads(days.written[0].read_text())
    assert d["day"] == "2026-03-02" and d["machine"] == "M1"
    for actuator, run in sessions[0].items():
        rr = reference_run(cfg, actuator, run, model_speeds=False)
        whole = {r["cause"]: r for r in fit_log(cfg, rr, actuator)}
        u = d["units"][actuator]
        assert u["stretches"] >= 1
        assert (u["increments"], u["holds"]) == (rr.n_increments, len(rr.holds))
        assert u["n_obs"] == whole["pump_leakage"]["n_obs"]
        for cause, row in whole.items():
            loss = np.asarray(u["causes"][cause]["loss"])
            assert np.argmin(loss) == np.argmin(row["loss"]), cause
            np.testing.assert_allclose(loss, row["loss"], rtol=0.05)
            # the day's largest increment change is the run's; the stretches' mean below it
            day = np.asarray(u["causes"][cause]["emax_day_mm"])
            np.testing.assert_allclose(day, row["emax_mm"], rtol=0.05, atol=1e-6)
            assert np.all(np.asarray(u["causes"][cause]["emax_sum_mm"]) / u["stretches"]
                          <= day + 1e-12)


def test_the_blocks_the_samples_come_in_change_nothing(cfg, sessions):
    whole = doc(summarise(cfg, sessions, close=False))["units"]
    same(doc(summarise(cfg, sessions, block_s=3.7, close=False))["units"], whole)
    assert whole["boom"]["stretches"] >= 1


def test_a_restart_goes_on_from_the_days_file(cfg, sessions, tmp_path):
    summarise(cfg, sessions[:1], tmp_path / "a")
    resumed = ds.DaySummaries(cfg, "M1", tmp_path / "a", lean=False, resume=True)
    summarise(cfg, sessions[1:], days=resumed)
    assert any("goes on from it" in n for n in resumed.notes)
    once = summarise(cfg, sessions, tmp_path / "b")
    a = json.loads((tmp_path / "a" / "M1_2026-03-02.summary.json").read_text())
    b = json.loads(once.written[0].read_text())
    same(a["units"], b["units"])
    assert a["first_s"] == b["first_s"]
    fresh = summarise(cfg, sessions[1:], tmp_path / "a")     # resume=False: replaced
    assert json.loads(fresh.written[0].read_text())["units"]["boom"]["stretches"] < \
        b["units"]["boom"]["stretches"]


def _select(run: Run, mask: np.ndarray) -> Run:
    """The samples of ``mask``; a switch's change timed only where its sample's period is
    whole (the sample before it kept)."""
    whole = mask & np.concatenate([[False], mask[:-1]])
    return Run(run.time_s[mask], run.speed_rpm[mask], run.torque_nm[mask],
               run.oil_temp_c[mask], run.position_mm[mask],
               refs={k: v[mask] for k, v in run.refs.items()},
               ref_edge_s={k: np.where(whole, v, np.nan)[mask]
                           for k, v in run.ref_edge_s.items()}, source="part")


def test_a_gap_ends_a_stretch_and_no_increment_spans_it(cfg, sessions):
    run = sessions[0]["boom"]
    t = run.time_s - run.time_s[0]
    days = summarise(cfg, [{"boom": _select(run, (t < 30.0) | (t > 31.0))}])
    u = doc(days)["units"]["boom"]
    halves = [reference_run(cfg, "boom", _select(run, m), model_speeds=False)
              for m in (t < 30.0, t > 31.0)]
    assert (u["increments"], u["holds"]) == (sum(rr.n_increments for rr in halves),
                                             sum(len(rr.holds) for rr in halves))


def test_midnight_ends_the_day_and_old_summaries_go(cfg, sessions, tmp_path):
    late = [{a: dataclasses.replace(r) for a, r in s.items()} for s in sessions]
    for run in late[1].values():
        run.shift_time(DAY0 + 86400.0 + 1800.0 - run.time_s[0])     # the next day, 00:30
    tmp_path.mkdir(exist_ok=True)
    old, other = tmp_path / "M1_2024-01-01.summary.json", tmp_path / "M2_2024-01-01.summary.json"
    old.write_text("{}")
    other.write_text("{}")
    days = summarise(cfg, late, tmp_path)
    first = json.loads((tmp_path / "M1_2026-03-02.summary.json").read_text())
    second = json.loads((tmp_path / "M1_2026-03-03.summary.json").read_text())
    assert first["complete"] and not second["complete"]
    assert first["units"]["boom"]["stretches"] >= 1 and second["units"]["boom"]["stretches"] >= 1
    assert not old.exists() and other.exists()
    assert len(days.written) == 2


def test_the_partial_day_is_written_every_save_interval(cfg, sessions, tmp_path):
    now = [0.0]
    days = ds.DaySummaries(cfg, "M1", tmp_path, lean=False, resume=True,
                           save_interval_s=300.0, clock=lambda: now[0])
    summarise(cfg, sessions, days=days, close=False)
    path = tmp_path / "M1_2026-03-02.summary.json"
    assert not path.exists()
    now[0] = 301.0
    days.feed("boom", None)
    partial = json.loads(path.read_text())
    assert not partial["complete"] and partial["units"]["boom"]["stretches"] >= 1
    days.save_interval_s = 0.0                  # written at every block, and at the stop
    days.close()
    assert json.loads(path.read_text())["units"] == days.document(days.days["2026-03-02"])[
        "units"]
    assert doc(days)["units"]["boom"]["stretches"] > partial["units"]["boom"]["stretches"]


def test_a_day_is_a_few_kilobytes(cfg, sessions, tmp_path):
    raw = summarise(cfg, sessions, tmp_path).written[0].read_bytes()
    assert len(raw) < 9000 and len(gzip.compress(raw)) < 4500
    assert ds.read_summary(raw, "x", cfg)["version"] == ds.VERSION


@pytest.fixture(scope="module")
def valid(cfg, sessions) -> dict:
    return doc(summarise(cfg, sessions[:1]))


@pytest.mark.parametrize("change, says", [
    (lambda d: "{not json", "not JSON"),
    (lambda d: {**d, "format": "something"}, "not a ddh-vsensor day summary"),
    (lambda d: {**d, "version": 99}, "version 99"),
    (lambda d: {**d, "physics_hash": "0" * 40}, "another configuration"),
    (lambda d: {**d, "machine": "a/b"}, "no machine name"),
    (lambda d: {**d, "day": "yesterday"}, "no date"),
    (lambda d: {k: v for k, v in d.items() if k != "grids"}, "incomplete"),
    (lambda d: {**d, "units": {"stick": d["units"]["boom"]}}, "not a unit"),
    (lambda d: {**d, "units": {"boom": {**d["units"]["boom"], "n_obs": -1}}}, "no count"),
    (lambda d: {**d, "units": {"boom": {**d["units"]["boom"], "causes": {
        **d["units"]["boom"]["causes"], "belt_slip": {
            "loss": [1.0], "emax_sum_mm": [0.0], "emax_day_mm": [0.0]}}}}},
     "one per grid value"),
    (lambda d: {**d, "grids": {**d["grids"], "belt_slip": [3.0, 2.0, 1.0] + [0.0] * 7}},
     "not increasing"),
])
def test_a_corrupt_summary_is_refused_in_one_line(cfg, valid, change, says):
    d = json.loads(json.dumps(valid))
    changed = change(d)
    data = changed.encode() if isinstance(changed, str) else json.dumps(changed).encode()
    with pytest.raises(ds.SummaryError) as err:
        ds.read_summary(data, "f.summary.json", cfg)
    assert says in str(err.value) and "\n" not in str(err.value)
    assert str(err.value).startswith("f.summary.json: ")


def test_nan_and_oversize_are_refused(cfg, valid):
    d = json.loads(json.dumps(valid))
    d["units"]["boom"]["causes"]["belt_slip"]["loss"][0] = float("nan")
    with pytest.raises(ds.SummaryError, match="not a finite number"):
        ds.read_summary(json.dumps(d).encode(), "x", cfg)
    with pytest.raises(ds.SummaryError, match="more than a summary's"):
        ds.read_summary(b" " * (ds.MAX_BYTES + 1), "x", cfg)


def test_its_rows_are_the_analysis_rows(cfg, valid):
    d = valid
    rows = ds.summary_rows(d)
    assert {(r["actuator"], r["cause"]) for r in rows} == {
        (a, c) for a in cfg.can.units for c in d["grids"]}
    row = next(r for r in rows if r["actuator"] == "boom" and r["cause"] == "time_offset")
    u = d["units"]["boom"]
    assert row["loss"] == u["causes"]["time_offset"]["loss"]
    assert row["n_obs"] == u["n_obs"] > row["n_increments"] > 0
    assert row["emax_mm"] == pytest.approx(
        np.asarray(u["causes"]["time_offset"]["emax_sum_mm"]) / u["stretches"])
    assert row["max_increment_mm"] == pytest.approx(u["max_increment_sum_mm"] / u["stretches"])
