"""The machine's CAN frames: the layout and each sensor's EDS generated from the configuration
(:mod:`.layout`, :mod:`.eds`) and the frame codec (:mod:`.dbc`). Reading and writing logs of
them is :mod:`ddh_vsensor.io`."""

from ddh_vsensor.canbus.dbc import (IO_MODULE, OIL_TEMP, FrameCodec, all_message_names, frame_ids,
                                    message_name)
from ddh_vsensor.canbus.eds import unit_object_dictionary
from ddh_vsensor.canbus.layout import machine_database

__all__ = ["IO_MODULE", "OIL_TEMP", "FrameCodec", "all_message_names", "frame_ids",
           "machine_database", "message_name", "unit_object_dictionary"]
