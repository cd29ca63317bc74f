"""CAN side of ddh-vsensor: the frame layout and sensor EDS generated from the configuration,
the frame codec, and CAN logs as measured runs."""

from .dbc import IO_MODULE, OIL_TEMP, FrameCodec, all_message_names, frame_ids, message_name
from .eds import unit_object_dictionary
from .layout import machine_database
from .log import read_can_log, write_blf

__all__ = ["IO_MODULE", "OIL_TEMP", "FrameCodec", "all_message_names", "frame_ids",
           "machine_database", "message_name", "read_can_log", "unit_object_dictionary",
           "write_blf"]
