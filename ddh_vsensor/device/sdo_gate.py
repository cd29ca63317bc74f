"""The gate in front of the emulated sensor's SDO server: CiA 301 says no SDO in STOPPED,
a segmented download is bounded by the size of its target object (aborted with 0607 0012,
never buffered beyond it), and a segment request with no transfer of its kind in progress is
answered with abort 0504 0001 (command specifier not valid).

canopen's ``SdoServer`` answers an upload segment request from whatever its buffer holds:
with no upload begun it raises TypeError inside (logged with a traceback, answered 0800 0000,
or not answered at all when no transfer ever began), after a segmented download it would send
that download's data back. Its invalid command specifiers are answered the same broken way
before the first transfer. The gate keeps those requests from it.
"""

from __future__ import annotations

import struct

import canopen
from canopen.sdo import SdoAbortedError

from ddh_vsensor.device.objects import ABORT_COMMAND, ABORT_LENGTH_TOO_HIGH, ABORT_READ_ONLY

TEXT_OBJECT_MAX_BYTES = 256         # download bound of an object without a fixed size
# client command specifiers (CiA 301, bits 5..7 of the first byte)
DOWNLOAD_SEGMENT, INITIATE_DOWNLOAD, INITIATE_UPLOAD = 0x00, 0x20, 0x40
UPLOAD_SEGMENT, ABORT_TRANSFER, BLOCK_UPLOAD, BLOCK_DOWNLOAD = 0x60, 0x80, 0xA0, 0xC0
TOGGLE = 0x10


class SdoGate:
    """Subscribed in place of the node's SDO server; passes on what CiA 301 allows."""

    def __init__(self, node: canopen.LocalNode, network: canopen.Network,
                 response_cob_id: int) -> None:
        self.node, self.network, self.response_cob_id = node, network, response_cob_id
        self.download_limit: int | None = None    # bytes, while a segmented download runs
        self.uploading = False                     # a segmented upload is in progress
        network.unsubscribe(node.sdo.rx_cobid, node.sdo.on_request)
        network.subscribe(node.sdo.rx_cobid, self.on_request)

    def reset(self) -> None:
        """No transfer in progress (an NMT reset ends them)."""
        self.download_limit = None
        self.uploading = False

    def on_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        if self.node.nmt.state in ("STOPPED", "INITIALISING") or len(data) != 8:
            return
        sdo = self.node.sdo
        ccs = data[0] & 0xE0
        if ccs == UPLOAD_SEGMENT:
            if not self.uploading:
                self.abort(sdo._index or 0, sdo._subindex or 0, ABORT_COMMAND)  # noqa: SLF001
                return
            in_step = data[0] & TOGGLE == sdo._toggle                          # noqa: SLF001
            sdo.on_request(can_id, data, timestamp)
            self.uploading = in_step and bool(sdo._buffer)                      # noqa: SLF001
            return
        self.uploading = False
        if ccs == INITIATE_DOWNLOAD and not data[0] & 0x02:     # initiate segmented download
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
        elif ccs == DOWNLOAD_SEGMENT:
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
            if ccs not in (INITIATE_DOWNLOAD, INITIATE_UPLOAD, ABORT_TRANSFER, BLOCK_UPLOAD,
                           BLOCK_DOWNLOAD):
                self.abort(sdo._index or 0, sdo._subindex or 0, ABORT_COMMAND)  # noqa: SLF001
                return
        before = sdo._buffer                                                    # noqa: SLF001
        sdo.on_request(can_id, data, timestamp)
        # canopen's server starts a segmented upload with a new buffer of the object's data
        self.uploading = ccs in (INITIATE_UPLOAD, BLOCK_UPLOAD) and \
            sdo._buffer is not before and bool(sdo._buffer)                     # noqa: SLF001

    def abort(self, index: int, subindex: int, code: int) -> None:
        self.network.send_message(self.response_cob_id,
                                  struct.pack("<BHBL", 0x80, index, subindex, code))
