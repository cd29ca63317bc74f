"""Movement tables: exact at the nodes, accurate between them, stored and refused correctly."""

import dataclasses
import json

import numpy as np
import pytest

from ddh_vsensor.physics.steady import holding_speed, steady_state, steady_state_at_torque
from ddh_vsensor.tables.store import TableError, load_unit_tables, save_unit_tables


@pytest.mark.parametrize("name", ["boom", "bucket"])
def test_full_table_is_the_steady_state_at_its_nodes(name, request, unit_tables):
    unit = request.getfixturevalue(name)
    full = unit_tables[name].full
    k = 6                                   # one temperature plane
    temp = full.temp.values()[k]
    exact = steady_state_at_torque(unit, full.speed.values()[:, None],
                                   full.torque.values()[None, :], temp)
    assert np.max(np.abs(full.velocity_mm_s[k] - exact.velocity_m_s * 1e3)) < 1e-8


@pytest.mark.parametrize("name", ["boom", "bucket"])
def test_interpolation_error_over_realistic_loads(name, request, unit_tables):
    unit = request.getfixturevalue(name)
    rng = np.random.default_rng(11)
    count = 50000
    n = rng.uniform(-6000, 6000, count)
    t = rng.uniform(0, 60, count)
    f = unit.load_force_n(rng.uniform(0, 1040, count)) * rng.uniform(0.8, 1.2, count)
    s = steady_state(unit, n, f, t)
    v, clamped = unit_tables[name].full.velocity_many(n, s.torque_nm, t)
    err = np.abs(v - s.velocity_m_s * 1e3)
    assert not clamped.any()
    assert err.mean() < 0.005 and err.max() < 0.5       # mm/s, against peaks of ~90-190 mm/s


def test_full_table_stands_still_at_the_holding_speed(boom, unit_tables):
    f = boom.load_force_n(0)
    h = holding_speed(boom, f, 27.0)
    s = steady_state(boom, h.speed_rpm, f, 27.0)
    v, _ = unit_tables["boom"].full.velocity(h.speed_rpm, float(s.torque_nm), 27.0)
    assert abs(v) < 0.01            # mm/s: < 0.1 mm over a 10 s hold
    # ... while the paper's per-revolution table creeps at the same point.
    mm_rev, _ = unit_tables["boom"].paper.movement_mm_per_rev(h.speed_rpm,
                                                              float(s.torque_nm), 27.0)
    assert mm_rev * h.speed_rpm / 60 > 0.1


def test_scalar_and_vectorised_lookups_agree_and_clamp(unit_tables):
    rng = np.random.default_rng(5)
    full, paper = unit_tables["bucket"].full, unit_tables["bucket"].paper
    n = rng.uniform(-7000, 7000, 500)
    q = rng.uniform(-200, 200, 500)
    t = rng.uniform(-20, 120, 500)
    v, c = full.velocity_many(n, q, t)
    m, cm = paper.movement_mm_per_rev_many(n, q, t)
    for i in range(500):
        vs, cs = full.velocity(n[i], q[i], t[i])
        ms, cms = paper.movement_mm_per_rev(n[i], q[i], t[i])
        assert vs == pytest.approx(v[i], abs=1e-9) and cs == c[i]
        assert ms == pytest.approx(m[i], abs=1e-9) and cms == cm[i]
    assert c.any() and (~c).any()
    inside = full.velocity(1000.0, -10.0, 27.0)
    assert inside[1] is False
    edge = full.velocity(1000.0, -10.0, 150.0)
    assert edge[1] is True and edge[0] == pytest.approx(full.velocity(1000.0, -10.0, 100.0)[0])


def test_paper_table_uses_three_speed_ranges(unit_tables):
    paper = unit_tables["boom"].paper
    assert paper.mm_per_rev.shape[:2] == (2, 3)
    a, _ = paper.movement_mm_per_rev(100.0, 22.0, 27.0)
    b, _ = paper.movement_mm_per_rev(1900.0, 22.0, 27.0)
    c, _ = paper.movement_mm_per_rev(2100.0, 22.0, 27.0)
    assert a == b != c


def test_store_round_trip_and_refusals(tmp_path, cfg, unit_tables):
    t = unit_tables["boom"]
    save_unit_tables(tmp_path, t)
    back = load_unit_tables(tmp_path, "boom", cfg)
    assert np.array_equal(back.full.velocity_mm_s, t.full.velocity_mm_s)
    assert back.meta["config_hash"] == cfg.physics_hash()
    other = dataclasses.replace(cfg, tables=dataclasses.replace(cfg.tables, torque_step_nm=1.0))
    with pytest.raises(TableError, match="another configuration.*tables build"):
        load_unit_tables(tmp_path, "boom", other)
    with pytest.raises(TableError, match="no table file"):
        load_unit_tables(tmp_path, "bucket", cfg)
    meta = dict(t.meta, format_version=99)
    save_unit_tables(tmp_path, dataclasses.replace(t, meta=meta))
    with pytest.raises(TableError, match="format 99"):
        load_unit_tables(tmp_path, "boom", cfg)
    (tmp_path / "boom.npz").write_bytes(b"not a zip")
    with pytest.raises(TableError, match="not a ddh-vsensor table"):
        load_unit_tables(tmp_path, "boom", cfg)


def test_metadata_is_plain_json(tables_dir):
    with np.load(tables_dir / "boom.npz", allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
    assert {"format_version", "config_hash", "grid", "units", "package_version"} <= set(meta)
