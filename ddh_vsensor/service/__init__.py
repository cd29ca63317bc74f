"""The daemon: Sevcon frames in, emulated CiA 406 position sensors out (see ``service``).

``service`` (the asyncio service: lifecycle, ticks, status), ``ingest`` (every received frame
routed by ID), ``unit_state`` (each cylinder's state: integration, gaps, staleness, presets,
what is published), ``persistence`` (estimates across restarts), ``bus`` (open, read, reconnect
one bus), ``buses`` (which buses a machine's frames are on), ``inputs`` (decode, check, count),
``limits`` (frame and log rates), ``heartbeat`` (NMT consumer), ``scheduler`` (absolute-deadline
ticks), ``sdnotify`` (systemd). The emulated sensor itself is :mod:`ddh_vsensor.device`.
"""

from ddh_vsensor.service.service import Service, ServiceOptions

__all__ = ["Service", "ServiceOptions"]
