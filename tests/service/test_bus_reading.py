"""The fd reader's coalescing: while frames keep coming they are read by a timer on the
service's grid, not per frame; once a read finds none the fd is watched again. Counted over
the reads' own times (a late wake under load only makes fewer reads)."""

from __future__ import annotations

import asyncio
import socket
import struct

import can

from ddh_vsensor.service.bus import BusLink, nonblocking_receiver

FRAME = struct.Struct("=IB3x8s")


class PairBus(can.BusABC):
    """SocketCAN's frame layout over an AF_UNIX seqpacket socket: recv(0) never blocks,
    fileno() is the socket."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        sock.setblocking(False)
        super().__init__(channel="pair")

    def _recv_internal(self, timeout):
        try:
            data = self.sock.recv(16)
        except BlockingIOError:
            return None, False
        can_id, dlc, payload = FRAME.unpack(data)
        return can.Message(arbitration_id=can_id, data=payload[:dlc],
                           is_extended_id=False), True

    def send(self, msg, timeout=None):
        raise NotImplementedError

    def fileno(self) -> int:
        return self.sock.fileno()


def test_reads_follow_the_grid_while_frames_come_then_the_fd_is_watched() -> None:
    period_s, frames_sent = 0.01, 60

    async def scenario():
        loop = asyncio.get_running_loop()
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        reads: list[tuple[float, int]] = []
        link = BusLink({"interface": "pair"}, None,
                       lambda batch: reads.append((loop.time(), len(batch))),
                       opener=lambda settings, filters: PairBus(mine), watch_fd=True,
                       coalesce_s=period_s)
        link.grid_anchor_s = loop.time() + 0.0037
        schedule = link._schedule_poll                                  # noqa: SLF001
        scheduled: list[tuple[float, float]] = []

        def recording(bus, generation) -> None:
            schedule(bus, generation)
            scheduled.append((loop.time(), link._rearm.when()))          # noqa: SLF001
        link._schedule_poll = recording                                 # noqa: SLF001
        await link.start()
        try:
            for _ in range(frames_sent):                  # one frame per millisecond
                theirs.send(FRAME.pack(0x181, 6, bytes(8)))
                await asyncio.sleep(0.001)
            for _ in range(200):                          # quiet: back to watching the fd
                await asyncio.sleep(0.005)
                if link._watching and link._rearm is None:             # noqa: SLF001
                    break
            watching = link._watching and link._rearm is None          # noqa: SLF001
            before = len(reads)
            theirs.send(FRAME.pack(0x181, 6, bytes(8)))
            for _ in range(200):
                await asyncio.sleep(0.005)
                if len(reads) > before:
                    break
        finally:
            await link.close()
            theirs.close()
        return link, reads, watching, before, scheduled

    link, reads, watching, before, scheduled = asyncio.run(scenario())
    assert sum(n for _, n in reads) == frames_sent + 1            # every frame, once
    assert watching and len(reads) == before + 1                   # the fd wakes it again
    # the burst: the first read woken by the fd, the rest by the timer, on the grid only
    assert before <= len(scheduled) + 1 and len(scheduled) >= 2
    whens = [when for _, when in scheduled]
    assert all(b - a > 0.999 * period_s for a, b in zip(whens, whens[1:]))   # one per period
    for now, when in scheduled:
        assert now < when <= now + period_s + 1e-9
        phase = (when - (link.grid_anchor_s or 0.0)) / period_s
        assert abs(phase - round(phase)) < 1e-6, (now, when)


class QueueBus(can.BusABC):
    """Frames from a list; ``kernel_filtered`` says whether they come already filtered."""

    def __init__(self, frames: list[can.Message], kernel_filtered: bool, **kwargs) -> None:
        self.frames, self.kernel_filtered = list(frames), kernel_filtered
        super().__init__(channel="queue", **kwargs)

    def _recv_internal(self, timeout):
        if not self.frames:
            return None, False
        return self.frames.pop(0), self.kernel_filtered

    def send(self, msg, timeout=None):
        raise NotImplementedError


def _frames(*ids: int) -> list[can.Message]:
    return [can.Message(arbitration_id=i, data=bytes([k]), is_extended_id=False)
            for k, i in enumerate(ids)]


def _drained(receive) -> list[tuple[int, bytes]]:
    out = []
    while (msg := receive()) is not None:
        out.append((msg.arbitration_id, bytes(msg.data)))
    return out


def test_the_fast_read_gives_what_python_can_recv_gives() -> None:
    ids = (0x181, 0x500, 0x182, 0x500, 0x181)
    filters = [{"can_id": 0x180, "can_mask": 0x7F0, "extended": False}]
    for kernel_filtered, kwargs in ((True, {}), (False, {}), (False, {"can_filters": filters})):
        by_recv = []
        bus = QueueBus(_frames(*ids), kernel_filtered, **kwargs)
        while bus.frames:               # python-can's recv(0) stops at a filtered-out frame
            msg = bus.recv(0.0)
            if msg is not None:
                by_recv.append((msg.arbitration_id, bytes(msg.data)))
        fast = _drained(nonblocking_receiver(QueueBus(_frames(*ids), kernel_filtered,
                                                      **kwargs)))
        assert fast == by_recv
        assert len(fast) == (3 if kwargs else 5)


def test_an_interface_with_its_own_recv_is_read_through_it() -> None:
    class OwnRecv(QueueBus):
        def recv(self, timeout=None):
            msg = super().recv(timeout)
            if msg is not None:
                msg.data = bytearray(b"own")
            return msg

    assert _drained(nonblocking_receiver(OwnRecv(_frames(0x181, 0x182), True))) == [
        (0x181, b"own"), (0x182, b"own")]


def test_a_drain_with_rounds_takes_the_frames_that_came_while_it_handled() -> None:
    async def scenario(rounds: int) -> tuple[int, list[int]]:
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        batches: list[int] = []

        def handle(batch) -> None:      # a controller's next frame comes during the handling
            batches.append(len(batch))
            if len(batches) == 1:
                theirs.send(FRAME.pack(0x182, 6, bytes(8)))

        link = BusLink({"interface": "pair"}, None, handle,
                       opener=lambda settings, filters: PairBus(mine), watch_fd=True,
                       coalesce_s=10.0)
        await link.start()
        link._loop.remove_reader(link._fd)                  # noqa: SLF001 - reads by drain only
        link._watching = False                              # noqa: SLF001
        try:
            theirs.send(FRAME.pack(0x181, 6, bytes(8)))
            theirs.send(FRAME.pack(0x181, 6, bytes(8)))
            got = link.drain(rounds)
        finally:
            await link.close()
            theirs.close()
        return got, batches

    assert asyncio.run(scenario(1)) == (2, [2])
    assert asyncio.run(scenario(3)) == (3, [2, 1])


def test_while_read_promptly_every_frame_is_read_as_it_comes() -> None:
    """Coalescing at 1 s: a frame sent while a poll is pending waits for it; once
    read_promptly is on, the pending poll gives way to the watched fd and each frame is read
    in the wake its arrival makes (counted over reads, not over time)."""

    async def scenario():
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        reads: list[int] = []
        link = BusLink({"interface": "pair"}, None, lambda batch: reads.append(len(batch)),
                       opener=lambda settings, filters: PairBus(mine), watch_fd=True,
                       coalesce_s=1.0)
        await link.start()
        frame = FRAME.pack(0x181, 8, bytes(8))
        theirs.send(frame)
        for _ in range(50):                  # the first wake reads it and starts coalescing
            await asyncio.sleep(0.001)
            if reads:
                break
        assert reads == [1] and link._rearm is not None               # noqa: SLF001
        theirs.send(frame)
        await asyncio.sleep(0.02)
        assert reads == [1]                  # waits for the coalescing poll, 1 s away
        link.read_promptly(True)
        for _ in range(50):
            await asyncio.sleep(0.001)
            if len(reads) == 2:
                break
        assert reads == [1, 1]
        for k in range(3):
            theirs.send(frame)
            for _ in range(50):
                await asyncio.sleep(0.001)
                if len(reads) == 3 + k:
                    break
            assert reads == [1] * (3 + k) and link._rearm is None      # noqa: SLF001
        link.read_promptly(False)
        await link.close()
        theirs.close()

    asyncio.run(scenario())
