"""Input checks without a bus: flood guard on frame time, rate-limited logging, Hall bits."""

from __future__ import annotations

import logging

import can

from ddh_vsensor.canbus.dbc import FrameCodec
from ddh_vsensor.service.inputs import Inputs
from ddh_vsensor.service.limits import RateLimitedLog, RateLimiter


def test_rate_limiter_counts_frame_time_not_arrival() -> None:
    limiter = RateLimiter(rate_hz=1000.0, burst=5)
    # a backlog of 1 kHz frames handled all at once is no flood: their own times are 1 ms apart
    assert all(limiter.take(100.0 + k * 1e-3) for k in range(1000))
    # 20 frames within 20 us are: the burst passes, the rest does not
    passed = sum(limiter.take(200.0 + k * 1e-6) for k in range(20))
    assert passed == 5
    assert not limiter.take(199.0)                 # time going back earns no tokens


def test_rate_limited_log_reports_what_it_held_back(caplog) -> None:
    limited = RateLimitedLog(logging.getLogger("t"), interval_s=3600.0)
    with caplog.at_level(logging.WARNING):
        for _ in range(5):
            limited.warning("k", "bad frame")
        limited.warning("other", "another kind")
    assert caplog.text.count("bad frame") == 1 and "another kind" in caplog.text
    limited._last["k"] = -1e9                     # interval over
    with caplog.at_level(logging.WARNING):
        limited.warning("k", "bad frame")
    assert "(+4 more since the last report)" in caplog.text


def test_hall_states_follow_the_configured_bits(cfg) -> None:
    codec = FrameCodec(cfg)
    inputs = Inputs(cfg, codec)
    assert inputs.refs("boom") is None
    msg = codec.encode_inputs({"boom": {"mid": 1}, "bucket": {"top": 1}}, 1.0)
    assert inputs.io(msg, 0.0)
    assert inputs.refs("boom") == {"bottom": False, "mid": True, "top": False}
    assert inputs.refs("bucket") == {"bottom": False, "mid": False, "top": True}


def test_rate_limiter_refills_after_its_clock_steps_back() -> None:
    """A frame clock stepped back 2 s must not starve the limiter until it catches up."""
    limiter = RateLimiter(rate_hz=100.0, burst=2)
    assert all(limiter.take(100.0 + k * 0.01) for k in range(100))
    assert sum(limiter.take(98.0 + k * 0.01) for k in range(1, 101)) >= 99


def test_hall_states_at_a_frame_time_are_those_of_the_io_frame_before_it(cfg) -> None:
    """A sample gets the state of the last I/O frame not younger than itself; before the
    first kept change, the oldest; with the clocks far apart (another epoch), the latest."""
    codec = FrameCodec(cfg)

    def inputs_with_changes() -> Inputs:
        inputs = Inputs(cfg, codec)
        for t, mid in ((1.0, 1), (1.1, 1), (1.5, 0), (1.6, 0)):
            assert inputs.io(codec.encode_inputs({"boom": {"mid": mid}}, t), 0.0)
        return inputs

    inputs = inputs_with_changes()
    assert inputs.refs("boom", 0.9)["mid"] is True
    assert inputs.refs("boom", 1.2)["mid"] is True
    assert inputs.refs("boom", 1.5)["mid"] is False
    assert inputs.refs("boom", 2.0)["mid"] is False
    assert inputs.refs("boom")["mid"] is False
    assert inputs_with_changes().refs("boom", 1.6 - 5.0)["mid"] is False
    # the I/O clock went back: what was kept before it no longer answers
    inputs = inputs_with_changes()
    assert inputs.io(codec.encode_inputs({"boom": {"mid": 1}}, 0.5), 0.0)
    assert inputs.refs("boom", 0.4)["mid"] is True


def test_a_drive_clock_stepping_back_does_not_bring_back_older_hall_states(cfg) -> None:
    """The drive's frame clock steps back 0.8 s while the I/O module, sending on change
    of state, has not sent since: looked up at the new clock's time, the kept changes would
    give the switch state of 0.8 s ago, an edge the rod never made (the fault campaign's
    references taken 20 mm off). A unit's states never go back to an older change; each
    unit keeps its own."""
    codec = FrameCodec(cfg)
    inputs = Inputs(cfg, codec)
    for t, mid in ((1.0, 1), (1.5, 0), (1.6, 0)):
        assert inputs.io(codec.encode_inputs({"boom": {"mid": mid}}, t), 0.0)
    assert inputs.refs("boom", 1.55)["mid"] is False
    assert inputs.refs("boom", 1.55 - 0.8)["mid"] is False
    assert inputs.refs("boom", 1.56 - 0.8)["mid"] is False
    assert inputs.refs("bucket", 1.2) == {"bottom": False, "mid": False, "top": False}
    # another unit's samples are behind this one's: its own lookup by time still holds
    assert inputs.io(codec.encode_inputs({"boom": {"mid": 1}}, 1.7), 0.0)
    assert inputs.refs("boom", 1.65)["mid"] is False
    assert inputs.refs("boom", 1.75)["mid"] is True
    assert inputs.refs("boom", 1.65)["mid"] is True


def test_an_io_module_sending_on_change_is_told_from_one_sending_every_sample(cfg) -> None:
    """Only frames sent on change of state time a switch's change finer than the samples:
    judged once each drive has sent IO_MODE_MIN_SAMPLES frames (100 Hz drives here; the
    module every 100 ms, or at every sample)."""
    from ddh_vsensor.service.inputs import IO_MODE_MIN_SAMPLES
    codec = FrameCodec(cfg)
    # (frames every n samples, a change's time after the sample before it): on change and
    # between samples; at every sample; on change but stamped with the samples' own times
    for every, change_s, timed in ((10, 0.0063, True), (1, 0.0063, False), (10, 0.01, False)):
        inputs = Inputs(cfg, codec)
        verdicts = []
        for k in range(1, 2 * IO_MODE_MIN_SAMPLES):
            t = k * 0.01
            if k % every == 0:
                inputs.io(codec.encode_inputs({"boom": {"mid": k // 50 % 2}}, t), t)
            if k % 50 == 49:                                  # a change before sample k + 1
                t_c = t + change_s
                inputs.io(codec.encode_inputs({"boom": {"mid": (k + 1) // 50 % 2}}, t_c), t_c)
            for a in cfg.unit_names:
                assert inputs.sevcon(a, codec.encode_sevcon(a, 10.0, 100.0, t), t) is not None
            verdicts.append(inputs.io_sends_on_change)
        assert not any(verdicts[:IO_MODE_MIN_SAMPLES - 1])
        later = verdicts[IO_MODE_MIN_SAMPLES:]
        assert later == [timed] * len(later), (every, change_s)


def test_a_remote_request_on_a_sensor_id_is_no_id_clash(cfg) -> None:
    """A master polling a TPDO by RTR asks for the sensor's frame; only a data frame on its
    ID is another sender."""
    inputs = Inputs(cfg, FrameCodec(cfg))
    node_id = cfg.can.units["boom"].sensor_node_id
    for can_id in (0x180 + node_id, 0x280 + node_id):
        inputs.clash(can.Message(arbitration_id=can_id, is_remote_frame=True, dlc=1,
                                 is_extended_id=False))
    assert inputs.counts["remote_requests"] == 2 and inputs.counts["id_clash"] == 0
    inputs.clash(can.Message(arbitration_id=0x180 + node_id, data=bytes(7),
                             is_extended_id=False))
    assert inputs.counts["id_clash"] == 1


def test_an_io_state_no_rod_position_gives_is_rejected(cfg) -> None:
    """A foreign frame on the I/O module's ID (a 1-byte "1": boom bottom, bucket mid and top)
    would be Hall edges, references where the rods are not: two of the bucket's switches
    425 mm apart cannot both see its magnet, so the frame is rejected, the states kept."""
    codec = FrameCodec(cfg)
    inputs = Inputs(cfg, codec)
    assert inputs.io(codec.encode_inputs({"boom": {"mid": 1}, "bucket": {}}, 1.0), 0.0)
    junk = can.Message(timestamp=1.01, arbitration_id=inputs.io_id, data=b"1",
                       is_extended_id=False)
    assert not inputs.io(junk, 0.0)
    assert inputs.counts["io_rejected"] == 1
    assert inputs.refs("bucket") == {"bottom": False, "mid": False, "top": False}
    # one switch per unit, however far from the estimate, is a rod position: taken
    assert inputs.io(codec.encode_inputs({"boom": {"top": 1}, "bucket": {"bottom": 1}}, 1.02),
                     0.0)
