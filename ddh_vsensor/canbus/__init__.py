"""CAN side of ddh-vsensor: the frame layout (DBC) and CAN logs as measured runs."""

from .dbc import (IO_MODULE, OIL_TEMP, FrameCodec, all_message_names, frame_ids,
                  load_dbc, message_name)
from .log import read_can_log, write_blf

__all__ = ["IO_MODULE", "OIL_TEMP", "FrameCodec", "all_message_names",
           "frame_ids", "load_dbc", "message_name", "read_can_log", "write_blf"]
