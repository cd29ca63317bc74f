"""Junk on a controller's heartbeat ID, however fast, does not take the real heartbeats'
place: frames that are no heartbeat are dropped before the rate limit, and the limit is per
reported state, so a flood repeating one state leaves another state's heartbeats through."""

from __future__ import annotations

import can

from ddh_vsensor.service import Service, ServiceOptions

from .conftest import channel_name


def _service(cfg, unit_tables, clock: list[float]) -> Service:
    return Service(cfg, unit_tables, {"interface": "virtual", "channel": channel_name()},
                   ServiceOptions(), clock=lambda: clock[0])


def test_junk_at_2000_per_s_on_the_heartbeat_id_drops_no_real_heartbeat(cfg,
                                                                        unit_tables) -> None:
    clock = [1000.0]
    service = _service(cfg, unit_tables, clock)
    hb_id = 0x700 + cfg.faults.heartbeat_node_ids["boom"]
    consumer = service.units["boom"].heartbeat
    assert consumer is not None
    junk = [bytes([0x31]), bytes([5, 0]), bytes(8), bytes([0x33])]
    real = 0
    for k in range(4000):                               # 2 s at 2000 frames/s
        clock[0] = 1000.0 + k * 0.0005
        data = bytes([5]) if k % 200 == 0 else junk[k % len(junk)]
        real += k % 200 == 0
        service.ingest.handle([can.Message(timestamp=clock[0], arbitration_id=hb_id,
                                           data=data, is_extended_id=False)], clock[0])
    assert consumer.count == real
    assert consumer.status(clock[0])[0]
    assert service.ingest.canopen_dropped == 4000 - real


def test_a_flood_repeating_one_state_leaves_the_other_state_through(cfg, unit_tables) -> None:
    """Stopped (4) at 1000/s, spoofed: limited; the controller's own OPERATIONAL heartbeats
    all arrive, so the consumer reports what it is told last, never loses them."""
    clock = [1000.0]
    service = _service(cfg, unit_tables, clock)
    hb_id = 0x700 + cfg.faults.heartbeat_node_ids["boom"]
    consumer = service.units["boom"].heartbeat
    assert consumer is not None
    for k in range(2000):
        clock[0] = 1000.0 + k * 0.001
        data = bytes([5]) if k % 100 == 50 else bytes([4])
        before = consumer.count
        service.ingest.handle([can.Message(timestamp=clock[0], arbitration_id=hb_id,
                                           data=data, is_extended_id=False)], clock[0])
        if data == bytes([5]):
            assert consumer.count == before + 1 and consumer.state == 5
    assert service.ingest.canopen_dropped > 1500
