"""What a unit counts as travel it did not integrate, when the clocks disagree: a frame clock
that stepped back during a gap (seen on another input or not) must not shorten the gap: the
interval this host measured between arrivals always counts; a wall clock step (frames stamped
by this host) is taken out of the interval, and a process preempted while it reads the two
clocks sees no step. And which Hall states a sample meets when the I/O module's frames are read ahead of it."""

from __future__ import annotations

import can
import pytest

from ddh_vsensor.canbus.dbc import FrameCodec
from ddh_vsensor.service import Service, ServiceOptions
from ddh_vsensor.service import unit_state as units_module

from .conftest import channel_name

PERIOD_S = 0.01
RPM = 1500.0


class Driven:
    """A service never started, driven frame by frame on its own monotonic clock."""

    def __init__(self, cfg, unit_tables) -> None:
        self.now = 1000.0
        self.wall_s = 1.8e9
        self.service = Service(cfg, unit_tables, {"interface": "virtual",
                                                  "channel": channel_name()},
                               ServiceOptions(), clock=lambda: self.now,
                               wall_clock=lambda: self.wall_s)
        self.codec = FrameCodec(cfg)

    def send(self, msg, now: float) -> None:
        self.now = now
        self.service.ingest.handle([msg], now)

    def run(self, units: tuple[str, ...], stamp0: float, now0: float, n: int) -> None:
        """``n`` frames of each of ``units`` every PERIOD_S; frame stamps from ``stamp0``
        (a clock that is not this host's), arrival from ``now0``."""
        for k in range(n):
            for unit in units:
                rpm = RPM if unit == "boom" else 0.0
                self.send(self.codec.encode_sevcon(unit, 4.0, rpm, stamp0 + k * PERIOD_S),
                          now0 + k * PERIOD_S)


@pytest.fixture
def driven(cfg, unit_tables) -> Driven:
    d = Driven(cfg, unit_tables)
    d.send(d.codec.encode_oil_temp(30.0, 50.0), d.now)
    d.run(("boom", "bucket"), 50.0, 1000.0, 50)          # 0.5 s of both, in step
    return d


def test_a_clock_step_back_during_a_gap_does_not_shorten_it(driven, cfg) -> None:
    boom = driven.service.units["boom"]
    widened = boom.gap_widening_mm
    # 0.6 s without boom frames; the bucket's go on, and their clock steps back 0.5 s
    driven.run(("bucket",), 50.5, 1000.5, 10)
    driven.run(("bucket",), 50.1, 1000.6, 50)
    driven.run(("boom", "bucket"), 50.6, 1001.1, 5)      # boom back: frame gap 0.1 s, truly 0.6
    arrival_gap_s = 1001.1 - (1000.0 + 49 * PERIOD_S)
    assert boom.gap_widening_mm - widened == pytest.approx(
        cfg.max_speed_mm_s("boom") * arrival_gap_s, rel=1e-6)


def test_an_arrival_gap_counts_whatever_the_frame_clock_says(driven, cfg, caplog) -> None:
    """Every input silent for 0.6 s, then frames whose clock reads on as if none were
    missing (stepped back by the outage: a hub passing a sender's stamps, an adapter whose
    own clock restarted): the interval this host measured is the gap, logged once."""
    boom = driven.service.units["boom"]
    widened = boom.gap_widening_mm
    driven.run(("boom", "bucket"), 50.5, 1001.1, 5)
    arrival_gap_s = 1001.1 - (1000.0 + 49 * PERIOD_S)
    assert boom.gap_widening_mm - widened == pytest.approx(
        cfg.max_speed_mm_s("boom") * arrival_gap_s, rel=1e-6)
    driven.run(("boom", "bucket"), 50.55, 1001.8, 5)
    assert sum("this host measured" in r.getMessage() and "boom" in r.getMessage()
               for r in caplog.records) == 1


def test_a_wall_clock_step_is_taken_out_of_the_frame_interval(driven) -> None:
    """Frames stamped by this host: the wall clock stepped back 1.5 s during a 2 s gap, so
    their interval says 0.5 s; the step against the monotonic clock gives the 2 s back. Read
    0.5 s after the last with no step, frames 10 ms apart: the 0.5 s this host measured."""
    boom = driven.service.units["boom"]
    wall_s = 1.8e9
    boom.last_rx_s, boom.last_wall_offset_s = 1000.0, wall_s - 1000.0
    assert boom.untracked_s(0.5, 1002.0, wall_s - 1.5 + 2.0, wall_s - 1.5 + 2.0,
                            wall_s - 1000.0 - 1.5) == pytest.approx(2.0)
    assert boom.untracked_s(0.01, 1000.5, wall_s + 0.01, wall_s + 0.5,
                            wall_s - 1000.0) == pytest.approx(0.5)


class _PreemptedClocks:
    """time.monotonic / time.time as a loaded host reads them: the first read of the pair is
    preempted for 20 ms between the wall clock and the monotonic one."""

    def __init__(self) -> None:
        self.mono_s, self.offset_s, self.reads = 1000.0, 1.8e9 - 1000.0, 0

    def monotonic(self) -> float:
        self.reads += 1
        if self.reads == 2:
            self.mono_s += 0.02
        self.mono_s += 1e-6
        return self.mono_s

    def time(self) -> float:
        return self.mono_s + self.offset_s


def test_a_preempted_clock_read_is_no_clock_step(driven, monkeypatch) -> None:
    """Preempted between the two clocks, a read of their difference is 10 ms off: read again,
    the narrowest read stands; and two reads whose difference is within their own error are
    no step (a step there would have counted 8 ms of phantom travel, and on a loaded
    controller a phantom gap forgets the Hall states: a reference missed)."""
    clocks = _PreemptedClocks()
    monkeypatch.setattr(units_module.time, "monotonic", clocks.monotonic)
    monkeypatch.setattr(units_module.time, "time", clocks.time)
    wall_s, offset_s, err_s = units_module.read_wall_offset()
    assert offset_s == pytest.approx(clocks.offset_s, abs=1e-5)
    assert err_s < 1e-5
    monkeypatch.undo()
    boom = driven.service.units["boom"]
    base_s = 1.8e9 - 1000.0
    boom.last_rx_s, boom.last_wall_offset_s, boom.last_wall_offset_err_s = 1000.0, base_s, 0.01
    assert boom.untracked_s(0.01, 1000.01, 1.8e9, 1.8e9, base_s - 0.008, 0.0) == 0.01
    boom.last_wall_offset_err_s = 0.0
    assert boom.untracked_s(0.01, 1000.01, 1.8e9, 1.8e9, base_s - 0.008, 0.0) == \
        pytest.approx(0.018, abs=1e-6)


def test_a_slow_event_timer_does_not_make_old_input_fresh(driven) -> None:
    """At a 1 s event timer, 0.1 s without Sevcon frames (10 of their periods) is stale: the
    published value would otherwise stand for motion it never saw, unflagged, for 3 s."""
    boom = driven.service.units["boom"]
    boom.tick_period_s = lambda: 1.0
    last = boom.last_rx_s
    assert not driven.service.stale(boom, last + 0.02)[0]
    assert driven.service.stale(boom, last + 0.1)[0]


def _over_the_mid_switch(cfg, unit_tables, io_ahead_s: float) -> float:
    """The boom driven over its mid switch (the Hall edge 0.3 s into the motion), the I/O
    frames handled ``io_ahead_s`` before the Sevcon frames of their time (the I/O module on
    another bus, read first); the position after the edge."""
    d = Driven(cfg, unit_tables)
    d.send(d.codec.encode_oil_temp(30.0, 50.0), d.now)
    frames = []
    for k in range(100):
        t = 50.0 + k * PERIOD_S
        frames.append((t, d.codec.encode_sevcon("boom", 4.0, RPM if k >= 10 else 0.0, t)))
        io = d.codec.encode_inputs({"boom": {"mid": int(k >= 40)}}, t + 0.5 * PERIOD_S)
        frames.append((t + 0.5 * PERIOD_S - io_ahead_s, io))
    for arrival, msg in sorted(frames, key=lambda f: f[0]):
        d.send(msg, 1000.0 + arrival - 50.0)
    boom = d.service.units["boom"]
    assert boom.references == 1
    return boom.estimator.position_mm


def test_io_frames_read_ahead_do_not_move_the_hall_edge(cfg, unit_tables) -> None:
    """Read 50 ms ahead (five Sevcon samples), the edge still falls on the sample of its
    time: the same position as with every frame in time order. Without the lookup by time
    the edge is taken five samples early: the boom's travel over 50 ms (1.3 mm here) off."""
    in_order = _over_the_mid_switch(cfg, unit_tables, 0.0)
    ahead = _over_the_mid_switch(cfg, unit_tables, 0.05)
    assert ahead == pytest.approx(in_order, abs=1e-9)


def test_io_frames_read_late_take_the_hall_edge_back_to_its_time(cfg, unit_tables) -> None:
    """Read 50 ms late, the edge is seen five samples after its time; taken back by their
    travel, at constant speed the position is that of frames in time order (to 0.01 mm; a
    late edge taken where seen is 1.3 mm off here)."""
    in_order = _over_the_mid_switch(cfg, unit_tables, 0.0)
    late = _over_the_mid_switch(cfg, unit_tables, -0.05)
    assert late == pytest.approx(in_order, abs=0.01)


def test_a_clock_step_back_brings_back_no_hall_state_of_before_it(cfg, unit_tables) -> None:
    """The I/O module sends on change of state and every 100 ms; 0.2 s after the boom passed
    its mid switch every frame clock steps back 0.4 s, to before the edge. The drive's frames
    show it at once, the module's only with its next frame: looked up at the new clock's
    times, the changes kept from the old one said the switch was off again: a second
    reference, which set the boom 5.8 mm back (in the fault campaign up to 23 mm, unflagged)."""
    d = Driven(cfg, unit_tables)
    d.send(d.codec.encode_oil_temp(30.0, 50.0), d.now)
    frames = []
    mid = None
    for k in range(100):
        t = 50.0 + k * PERIOD_S
        stamp = t - (0.4 if k >= 60 else 0.0)
        frames.append((t, d.codec.encode_sevcon("boom", 4.0, RPM if k >= 10 else 0.0, stamp)))
        change = int(k >= 40) != mid
        mid = int(k >= 40)
        if change or k % 10 == 3:
            frames.append((t + 0.5 * PERIOD_S, d.codec.encode_inputs(
                {"boom": {"mid": mid}}, stamp + 0.5 * PERIOD_S)))
    for arrival, msg in sorted(frames, key=lambda f: f[0]):
        d.send(msg, 1000.0 + arrival - 50.0)
    boom = d.service.units["boom"]
    assert boom.references == 1


SLOW_PERIOD_S = 0.002             # 500 Hz input: a fixed tick would publish values this old


class Held:
    """The boom at 500 Hz, frames stamped by this host's wall clock (as SocketCAN stamps
    them); the tick driven by hand, the release timer's loop never run."""

    def __init__(self, cfg, unit_tables) -> None:
        import asyncio
        self.d = Driven(cfg, unit_tables)
        self.service = self.d.service
        self.service._loop = asyncio.new_event_loop()              # noqa: SLF001
        for unit in self.service.units.values():
            unit.node.boot()
        self.boom = self.service.units["boom"]
        self.d.send(self.d.codec.encode_oil_temp(30.0, 50.0), self.d.now)

    def frames(self, n: int, last_age_s: float) -> None:
        """``n`` boom frames, the last ``last_age_s`` old by the wall clock now."""
        t_last = self.d.wall_s - last_age_s
        for k in range(n):
            t = t_last - (n - 1 - k) * SLOW_PERIOD_S
            self.d.send(self.d.codec.encode_sevcon("boom", 4.0, RPM, t),
                        self.d.now + SLOW_PERIOD_S)

    def tick(self) -> None:
        self.service._on_tick(self.d.now, 0)                       # noqa: SLF001

    def close(self) -> None:
        self.service._loop.close()                                 # noqa: SLF001


@pytest.fixture
def held(cfg, unit_tables):
    h = Held(cfg, unit_tables)
    yield h
    h.close()


def test_a_fresh_input_is_published_at_the_tick(held, cfg) -> None:
    held.frames(20, 0.5 * cfg.can.fresh_input_ms / 1000.0)
    held.tick()
    assert "boom" not in held.service._held                        # noqa: SLF001
    assert held.boom.node._tick == held.service._tick_index        # noqa: SLF001


def test_an_old_input_waits_for_the_next_frame_and_goes_out_with_it(held, cfg) -> None:
    """The newest frame 1.5 ms old at the tick (fresh: 1 ms): the position waits for the next
    frame, due 0.5 ms later, and is published with it; what goes out then includes it."""
    held.frames(20, 0.0015)
    held.tick()
    assert "boom" in held.service._held                            # noqa: SLF001
    published = held.service.frames_published
    seen = []
    held.service.observers.append(lambda unit, p, t: seen.append((unit, p.input_frames, t)))
    held.d.wall_s += 0.0005
    held.frames(1, 0.0)
    assert held.service.frames_published > published
    received = held.service.inputs.units["boom"].received
    assert ("boom", received, held.boom.last_frame_t) in seen
    assert not held.service._held and held.service._release is None   # noqa: SLF001


def test_a_held_position_goes_out_when_its_frame_does_not_come(held) -> None:
    """The hold is bounded by the timer (here called by hand) and by the next tick."""
    held.frames(20, 0.0015)
    held.tick()
    handle = held.service._release                                  # noqa: SLF001
    assert handle is not None
    published = held.service.frames_published
    handle._run()                                                   # noqa: SLF001
    assert held.service.frames_published > published and not held.service._held  # noqa: SLF001


def test_an_overdue_frame_is_not_waited_for(held) -> None:
    """Older than a period and its slack: the controller stopped or a frame was lost."""
    held.frames(20, 1.5 * SLOW_PERIOD_S)
    held.tick()
    assert "boom" not in held.service._held                        # noqa: SLF001



def test_a_synchronous_tpdo_is_sent_on_sync_and_its_bus_read_as_frames_come(held) -> None:
    """A master makes the boom's TPDO1 synchronous (type 1): each SYNC sends it at once with
    the position as it stands, and the bus is read as frames come (a reading period later
    would answer the SYNC up to 5 ms late); back on its timer, reading coalesces again."""
    service, boom = held.service, held.boom
    link = service.links["default"]
    sync = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False,
                       timestamp=held.d.wall_s)
    held.frames(20, 0.0)
    boom.node.node.set_data(0x1800, 2, bytes([1]), check_writable=True)
    assert boom.node.synchronous and not boom.node.due(service._tick_index + 10)  # noqa: SLF001
    for _ in range(3):
        published = service.frames_published
        held.d.send(sync, held.d.now)
        assert service.frames_published == published + 1
        assert link.prompt
    boom.node.node.set_data(0x1800, 2, bytes([254]), check_writable=True)
    held.d.send(sync, held.d.now)
    assert not boom.node.synchronous and not link.prompt


def test_stamps_steadily_behind_the_wall_clock_are_learnt_not_stale_forever(driven,
                                                                             monkeypatch) -> None:
    """Frames stamped 0.8 s behind this host's wall clock (a sender's clock a hub passes on):
    stale at first (delivered late, as far as anyone can tell), then, the lag steady for
    LATE_LEARN_S, taken as that clock's offset; a lag that grows beyond it is late again.
    The wall clock here runs with the test's monotonic one."""
    boom = driven.service.units["boom"]
    monkeypatch.setattr(units_module.time, "time", lambda: 1.8e9 + driven.now)
    monkeypatch.setattr(units_module.time, "monotonic", lambda: driven.now)

    def send(k: int, lag_s: float) -> None:
        for unit in ("boom", "bucket"):
            driven.now += PERIOD_S / 2
            driven.send(driven.codec.encode_sevcon(unit, 4.0, 0.0, 1.8e9 + driven.now - lag_s),
                        driven.now)

    send(0, 0.8)
    assert "delivered late" in driven.service.stale(boom, driven.now)[1]
    for k in range(int(units_module.LATE_LEARN_S / PERIOD_S * 0.5)):
        send(k, 0.8)
    assert driven.service.stale(boom, driven.now)[0]                    # not yet steady
    for k in range(int(units_module.LATE_LEARN_S / PERIOD_S * 0.6)):
        send(k, 0.8)
    assert boom.stamp_offset_s == pytest.approx(0.8, abs=0.01)
    assert not driven.service.stale(boom, driven.now)[0]
    send(0, 1.5)
    assert "delivered late" in driven.service.stale(boom, driven.now)[1]
