"""The daemon: Sevcon frames in, emulated CiA 406 position sensors out (see ``service``).

``bus`` (open, read, reconnect), ``inputs`` (decode, check, count), ``heartbeat`` (NMT
consumer), ``node`` (CiA 406 LocalNode per cylinder), ``scheduler`` (absolute-deadline ticks),
``sdnotify`` (systemd), ``service`` (the asyncio service), ``replay`` (timed log replay),
``watch`` (the sensors as a listener sees them).
"""

from .service import Service, ServiceOptions

__all__ = ["Service", "ServiceOptions"]
