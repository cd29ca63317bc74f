"""Fixtures shared across the test tree: the reference config, its units and built tables;
synthetic days of evidence (the trend's, the health's and the daemon's tests)."""

from __future__ import annotations

import os

# One BLAS thread per test process: pytest -n 2 on two cores runs two processes already, and
# their BLAS threads only compete (a 200-cell Kalman threshold: 4.4 s threaded, 0.3 s not).
# Set before numpy is first imported in a worker; where it already was, this changes nothing.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib
import datetime as dt
import fcntl
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from ddh_vsensor.config import Config, load_config
from ddh_vsensor.diagnosis.day_summary import Day, DaySummaries, UnitDay
from ddh_vsensor.diagnosis.evidence import GRIDS
from ddh_vsensor.diagnosis.trend import DAY_S
from ddh_vsensor.physics.unit import DDHUnit
from ddh_vsensor.sim.cycles import Profile, Trajectory
from ddh_vsensor.tables.build import build_unit_tables
from ddh_vsensor.tables.lookup import UnitTables
from ddh_vsensor.tables.store import save_unit_tables

REPO = Path(__file__).resolve().parents[1]

# The modules that take tens of seconds, longest first (durations of a whole run, -n 2): run
# before the rest, so that under --dist loadfile the two workers end together instead of one
# finishing a long module alone (xdist's own order, by number of tests, put these last).
LONG_FIRST = (
    "tests/diagnosis/test_hidden_effects.py", "tests/diagnosis/test_baseline.py",
    "tests/faults/test_bus_faults.py", "tests/commission/test_flow.py",
    "tests/machines/test_machines_cli.py", "tests/faults/test_clock_outage.py",
    "tests/service/test_health_replay.py", "tests/diagnosis/test_references.py",
    "tests/docs/test_readme.py", "tests/service/test_cold_start.py",
    "tests/service/test_cli.py", "tests/service/test_soak_smoke.py",
)


def pytest_configure(config: pytest.Config) -> None:
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The long modules first, each module's tests in their own order."""
    rank = {path: i for i, path in enumerate(LONG_FIRST)}

    def key(item: pytest.Item) -> int:
        path = Path(str(item.path)).resolve().relative_to(REPO).as_posix()
        return rank.get(path, len(rank))
    items.sort(key=key)


@pytest.fixture(scope="session")
def cfg() -> Config:
    return load_config(REPO / "config" / "loader.yaml")


@pytest.fixture(scope="session")
def boom(cfg: Config) -> DDHUnit:
    return DDHUnit.from_config(cfg, "boom")


@pytest.fixture(scope="session")
def bucket(cfg: Config) -> DDHUnit:
    return DDHUnit.from_config(cfg, "bucket")


@pytest.fixture(scope="session")
def unit_tables(cfg: Config) -> dict[str, UnitTables]:
    return {a: build_unit_tables(cfg, a) for a in ("boom", "bucket")}


@pytest.fixture(scope="session")
def tables_dir(tmp_path_factory: pytest.TempPathFactory,
               unit_tables: dict[str, UnitTables]) -> Path:
    out = tmp_path_factory.mktemp("tables")
    for t in unit_tables.values():
        save_unit_tables(out, t)
    return out


@pytest.fixture(scope="session")
def short_profile() -> Profile:
    """7 s: the boom lifts through its middle switch and back down, the bucket retracts and
    extends through its middle switch (smooth moves at about speed 4), then both hold."""
    boom = Trajectory(np.array([0.0, 0.5, 3.0, 3.5, 6.0, 7.0]),
                      np.array([1.5, 1.5, 170.0, 170.0, 1.5, 1.5]))
    bucket = Trajectory(np.array([0.0, 0.3, 2.4, 2.8, 4.9, 7.0]),
                        np.array([600.0, 600.0, 300.0, 300.0, 600.0, 600.0]))
    return Profile("test short", {"boom": boom, "bucket": bucket}, 7.0)


# --- synthetic days of evidence --------------------------------------------------------------

T0 = 1.767e9
MACHINE = "M07"


def rows(true_u_per_day, cause="pump_leakage", others=("displacement", "time_offset"),
         noise=0.02, seed=0, mm_per_u=8.0):
    """Per day and cause a row as :mod:`ddh_vsensor.fleet.analysis` writes it: squared error
    of 20 observations around the day's true parameter (log scale for factors)."""
    return mixed_rows({cause: (mm_per_u, true_u_per_day)}, others, noise, seed)


def mixed_rows(shown, others, noise, seed):
    """Rows where each cause of ``shown`` (cause -> (mm per unit, true parameter per day))
    shows in the references and the ``others`` explain nothing."""
    rng = np.random.default_rng(seed)
    out = []
    for day in range(len(next(iter(shown.values()))[1])):
        obs = {c: (m, u[day] + rng.normal(0.0, noise)) for c, (m, u) in shown.items()}
        sse_nominal = 20.0 * (1.0 + sum((m * v) ** 2 for m, v in obs.values()))
        for c in (*shown, *others):
            grid = np.asarray(GRIDS[c], float)
            gu = np.log(grid) if c in ("pump_leakage", "displacement") else grid
            if c in obs:
                m, v = obs[c]
                rest = sum((mm * vv) ** 2 for cc, (mm, vv) in obs.items() if cc != c)
                sse = 20.0 * (1.0 + (m * (gu - v)) ** 2 + rest)
                emax = m * np.abs(gu)
            else:                               # explains nothing
                sse = np.full(len(grid), sse_nominal) + 5.0 * gu ** 2
                emax = np.abs(gu)
            out.append({"cause": c, "grid": list(grid), "loss": list(sse),
                        "emax_mm": list(emax), "n_obs": 20, "loss_nominal": sse_nominal,
                        "max_increment_mm": 1.0, "time_s": T0 + day * DAY_S,
                        "log_id": f"d{day}"})
    return out


def wearing(days: int, seed: int = 0) -> list[dict]:
    """A pump leakage rising 3 % a day from day 3 (8 mm per unit of its log)."""
    u = np.log(1.0 + 0.03 * np.maximum(np.arange(days) - 3, 0))
    return mixed_rows({"pump_leakage": (8.0, u)}, ("displacement", "time_offset"), 0.02, seed)


def steady(days: int, seed: int = 5) -> list[dict]:
    """A pump leakage 5 % above nominal, day after day."""
    u = np.full(days, np.log(1.05))
    return mixed_rows({"pump_leakage": (8.0, u)}, ("displacement", "time_offset"), 0.02, seed)


def day_docs(cfg: Config, per_unit_rows: dict[str, list[dict]]) -> list[dict]:
    """Day summaries of :data:`MACHINE` holding the rows (one stretch a day), as the daemon
    writes them."""
    days = DaySummaries(cfg, MACHINE, None)
    by_day: dict[float, dict[str, UnitDay]] = {}
    for actuator, unit_rows in per_unit_rows.items():
        for r in unit_rows:
            u = by_day.setdefault(r["time_s"], {}).setdefault(actuator, UnitDay())
            u.loss[r["cause"]] = np.asarray(r["loss"], float)
            u.emax_sum_mm[r["cause"]] = np.asarray(r["emax_mm"], float)
            u.emax_day_mm[r["cause"]] = np.asarray(r["emax_mm"], float)
            u.n_obs = u.n_increments = r["n_obs"]
            u.loss_nominal, u.stretches = r["loss_nominal"], 1
            u.max_increment_sum_mm = u.max_increment_day_mm = r["max_increment_mm"]
    docs = []
    for t, units in sorted(by_day.items()):
        day = dt.datetime.fromtimestamp(t, dt.timezone.utc).date().isoformat()
        docs.append(days.document(Day(day, units, t, t + 3600.0, True)))
    return docs


@pytest.fixture(scope="session")
def wear_days(cfg: Config) -> Callable[[int], list[dict]]:
    """``days`` day summaries of a machine whose boom's pumps wear (alarmed from about day
    11) and whose bucket's stay 5 % off."""
    boom, bucket = cfg.unit_names[:2]
    return lambda days: day_docs(cfg, {boom: wearing(days), bucket: steady(days)})


# --- built once per run --------------------------------------------------------------------


def shared_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The run's temporary directory every pytest-xdist worker shares (without xdist the
    session's own)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@contextlib.contextmanager
def built_once(path: Path) -> Iterator[bool]:
    """Whether the caller has to build ``path`` (True: it does, under a lock every worker
    of the run takes; False: another process built it, complete). A build that fails
    leaves it to the next caller."""
    path.parent.mkdir(parents=True, exist_ok=True)
    complete = path.with_name(path.name + ".complete")
    with open(path.with_name(path.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if complete.exists():
            yield False
            return
        if path.exists():
            shutil.rmtree(path)
        yield True
        complete.touch()


@pytest.fixture(scope="session")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """:func:`shared_root`, for test packages that cannot import this module."""
    return shared_root(tmp_path_factory)


@pytest.fixture(scope="session")
def build_once() -> Callable[[Path], contextlib.AbstractContextManager[bool]]:
    """:func:`built_once`, for test packages that cannot import this module."""
    return built_once
