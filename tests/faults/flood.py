"""A flooding bus participant as its own process:
``python -m faults.flood URL KIND RATE_HZ DURATION_S`` (run from tests/), paced every 5 ms.
Kinds: ``nmt_reset`` (broadcast reset node), ``bus_off`` (error frames), ``random_ext``
(random 29-bit IDs), ``sdo_segments`` (an endless segmented SDO download to the boom sensor,
node ID as a fifth argument). Prints the number of frames sent."""

from __future__ import annotations

import random
import sys
import time

import can


def make_frames(kind: str, node_id: int = 49):
    rng = random.Random(9)
    if kind == "nmt_reset":
        msg = can.Message(arbitration_id=0, data=[0x81, 0], is_extended_id=False)
        return lambda k: msg
    if kind == "bus_off":
        msg = can.Message(arbitration_id=0x40, is_error_frame=True, data=bytes(8),
                          is_extended_id=False)
        return lambda k: msg
    if kind == "random_ext":
        return lambda k: can.Message(arbitration_id=rng.getrandbits(29), data=b"\x00",
                                     is_extended_id=True)
    if kind == "sdo_segments":
        initiate = can.Message(arbitration_id=0x600 + node_id, is_extended_id=False,
                               data=[0x21, 0x10, 0x60, 0x01, 0, 0, 0, 0])
        return lambda k: initiate if k % 5000 == 0 else can.Message(
            arbitration_id=0x600 + node_id, is_extended_id=False,
            data=[(k % 2) << 4] + [0x55] * 7)
    raise SystemExit(f"unknown kind {kind}")


def main(argv: list[str]) -> int:
    url, kind, rate_hz, duration_s = argv[0], argv[1], float(argv[2]), float(argv[3])
    make = make_frames(kind, int(argv[4]) if len(argv) > 4 else 49)
    bus = can.Bus(interface="remote", channel=url)
    sent = 0
    try:
        start = time.time()
        while time.time() - start < duration_s:
            due = int((time.time() - start) * rate_hz)
            while sent < due:
                bus.send(make(sent))
                sent += 1
            time.sleep(0.005)
    finally:
        bus.shutdown()
    print(sent, start, time.time())
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
