"""The daemon: Sevcon frames in, emulated CiA 406 position sensors out (see ``service``).

``service`` (the asyncio service: lifecycle, ticks, status), ``ingest`` (every received frame
routed by ID), ``units`` (each cylinder's state: integration, gaps, staleness, presets, what is
published), ``persistence`` (estimates across restarts), ``bus`` (open, read, reconnect one
bus), ``buses`` (which buses a machine's frames are on), ``inputs`` (decode, check, count),
``heartbeat`` (NMT consumer), ``node`` (CiA 406 LocalNode per cylinder) with ``objects``,
``pdo``, ``emcy``, ``guarding``, ``sdo_gate`` and ``network``, ``client`` (the master's side:
SDO/NMT client of a sensor), ``scheduler`` (absolute-deadline ticks), ``sdnotify`` (systemd),
``replay`` (timed log replay, a machine's frames), ``watch`` (the sensors as a listener sees
them).
"""

from .service import Service, ServiceOptions

__all__ = ["Service", "ServiceOptions"]
