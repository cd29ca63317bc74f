"""The gate in front of the emulated sensor's SDO server: CiA 301 says no SDO in STOPPED,
and a segmented download is bounded by the size of its target object (aborted with
0607 0012, never buffered beyond it)."""

from __future__ import annotations

import struct

import canopen
from canopen.sdo import SdoAbortedError

from ddh_vsensor.device.objects import ABORT_COMMAND, ABORT_LENGTH_TOO_HIGH, ABORT_READ_ONLY

TEXT_OBJECT_MAX_BYTES = 256         # download bound of an object without a fixed size


class SdoGate:
    """Subscribed in place of the node's SDO server; passes on what CiA 301 allows."""

    def __init__(self, node: canopen.LocalNode, network: canopen.Network,
                 response_cob_id: int) -> None:
        self.node, self.network, self.response_cob_id = node, network, response_cob_id
        self.download_limit: int | None = None    # bytes, while a segmented download runs
        network.unsubscribe(node.sdo.rx_cobid, node.sdo.on_request)
        network.subscribe(node.sdo.rx_cobid, self.on_request)

    def on_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self.node.nmt.state in ("STOPPED", "INITIALISING") or len(data) != 8:
            return
        ccs = data[0] & 0xE0
        if ccs == 0x20 and not data[0] & 0x02:         # initiate segmented download
            self.download_limit = None
            index, subindex = struct.unpack_from("<HB", data, 1)
            try:
                obj = self.node._find_object(index, subindex)   # noqa: SLF001
            except SdoAbortedError as exc:
                self.abort(index, subindex, exc.code)
                return
            if not obj.writable:
                self.abort(index, subindex, ABORT_READ_ONLY)
                return
            limit = len(obj) // 8 if obj.data_type in canopen.objectdictionary.NUMBER_TYPES \
                else TEXT_OBJECT_MAX_BYTES
            if data[0] & 0x01 and struct.unpack_from("<I", data, 4)[0] > limit:
                self.abort(index, subindex, ABORT_LENGTH_TOO_HIGH)
                return
            self.download_limit = limit
        elif ccs == 0x00:                               # download segment
            sdo = self.node.sdo
            if self.download_limit is None:
                self.abort(sdo._index or 0, sdo._subindex or 0, ABORT_COMMAND)  # noqa: SLF001
                return
            size = 7 - ((data[0] >> 1) & 0x07)
            if len(sdo._buffer) + size > self.download_limit:                 # noqa: SLF001
                self.download_limit, sdo._buffer = None, None                   # noqa: SLF001
                self.abort(sdo._index, sdo._subindex, ABORT_LENGTH_TOO_HIGH)    # noqa: SLF001
                return
            if data[0] & 0x01:                          # last segment
                self.download_limit = None
        else:
            self.download_limit = None
        self.node.sdo.on_request(can_id, data, timestamp)

    def abort(self, index: int, subindex: int, code: int) -> None:
        self.network.send_message(self.response_cob_id,
                                  struct.pack("<BHBL", 0x80, index, subindex, code))
