"""Every input silent while the bucket rises, then frames whose clock stepped back by about the
outage: nothing was seen going back (no frame came during it), so only this host's own
arrival clock knows the gap. Against ``ddh-vsensor run`` on a python-can-remote hub, the
simulated paper cycle in real time: no published value beyond its uncertainty without a flag.

Variants: a hub passing a sender's own (wall-clock) stamps, the sender's clock 2.95 s fast
and set right (2.965 s back) in a 3 s outage; an adapter with its own hardware clock (uptime,
not the wall clock) that was reset in the outage, its driver carrying on from the last stamp
it knew; a short outage (0.6 s), the sender's clock 0.55 s fast and stepped 0.565 s back."""

from __future__ import annotations

import can
import pytest

from ddh_vsensor.canbus.dbc import FrameCodec, message_name

from .conftest import run_row
from .harness import EXPLAINING, check_invariant, outputs

# The bucket is preset at rest at 0.5 s, meets its switches lowering 600 -> 200 mm (confirmed
# by them), rests, and rises 200 -> 700 mm from 8.8 s to 12.2 s.
T0, T1 = 0.5, 14.0
ADAPTER_START_S = 1000.0        # the hardware clock's reading at T0 (uptime)

VARIANTS = {
    # outage start and end, how fast the sender's clock runs before it, how far it steps
    # back in it, and whether it is an adapter's own clock (else the sender's wall clock)
    "hub passes a sender's stamps, 3 s": (9.0, 12.0, 2.95, 2.965, False),
    "hardware clock reset, 3 s": (9.0, 12.0, 0.0, 2.965, True),
    "hub passes a sender's stamps, 0.6 s": (10.0, 10.6, 0.55, 0.565, False),
}


def _stamp(end: float, ahead: float, back: float, adapter: bool):
    def stamp(t: float, base_wall: float) -> float:
        shifted = t + ahead - (back if t >= end else 0.0)
        return (ADAPTER_START_S + shifted - T0) if adapter else base_wall + shifted
    return stamp


def _true_times(frames: list[can.Message], paper_frames: list[can.Message],
                base_wall: float) -> list[can.Message]:
    """The recorded frames, each input frame stamped with its true (wall) time: the k-th
    recorded frame on an input ID is the k-th sent on it (the invariant's interval starts at
    the newest integrated frame's true time)."""
    sent: dict[int, list[float]] = {}
    for m in paper_frames:
        sent.setdefault(m.arbitration_id, []).append(base_wall + m.timestamp)
    seen: dict[int, int] = {}
    out = []
    for m in frames:
        times = sent.get(m.arbitration_id)
        if times is None:
            out.append(m)
            continue
        k = seen.get(m.arbitration_id, 0)
        seen[m.arbitration_id] = k + 1
        out.append(can.Message(timestamp=times[min(k, len(times) - 1)],
                               arbitration_id=m.arbitration_id, data=m.data,
                               is_extended_id=m.is_extended_id))
    return out


@pytest.mark.parametrize("variant", VARIANTS.values(), ids=VARIANTS)
def test_an_outage_hiding_a_frame_clock_step_is_no_unflagged_error(cfg, cfg_raw, paper, hub,
                                                                   tmp_path, variant) -> None:
    start, end, ahead, back, adapter = variant

    def silent(m: can.Message) -> bool:
        return start <= m.timestamp < end

    row = run_row(hub, tmp_path, cfg, cfg_raw, paper, T0, T1, drop=silent,
                  stamp=_stamp(end, ahead, back, adapter))
    assert row.exit_code == 0
    sent = [m for m in paper.segment(T0, T1) if not silent(m)]
    frames = _true_times(row.frames, sent, row.base_wall)
    for a in ("bucket", "boom"):
        v = check_invariant(cfg, frames, a, paper.truth_t[a], paper.truth_mm[a], row.base_wall)
        assert v.outputs > 500, (a, v.describe())
        assert not v.violations, (a, v.describe(), row.daemon.log()[-3000:])
    # the invariant has teeth: the bucket was confirmed before the outage, unflagged
    bucket = outputs(cfg, row.frames, "bucket")
    sevcon = FrameCodec(cfg).ids[message_name("sevcon", "bucket")]
    before = sum(1 for m in sent if m.arbitration_id == sevcon and m.timestamp < start)
    assert sum(1 for o in bucket if o.input_frames < before and not o.flags & EXPLAINING) > 100
    assert "this host measured" in row.daemon.log()
