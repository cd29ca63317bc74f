"""systemd's sd_notify protocol in the standard library: READY, STATUS, WATCHDOG, STOPPING.

A datagram to the AF_UNIX socket named by ``NOTIFY_SOCKET`` (``@`` = abstract namespace).
Without ``NOTIFY_SOCKET`` (not started by systemd) every call is a no-op. A failed send is
logged, never raised: telling systemd about the service must not stop the service. The
watchdog interval is half of ``WATCHDOG_USEC`` (as sd_watchdog_enabled(3) recommends), and
only when ``WATCHDOG_PID`` is unset or names this process. Sends never block (MSG_DONTWAIT):
a notify socket whose queue is full loses the message, not the service its timing.
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)


class SystemdNotifier:
    def __init__(self, environ: dict[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self.address = env.get("NOTIFY_SOCKET") or None
        self.watchdog_interval_s: float | None = None
        usec, pid = env.get("WATCHDOG_USEC"), env.get("WATCHDOG_PID")
        if usec and (not pid or pid == str(os.getpid())):
            try:
                self.watchdog_interval_s = int(usec) / 2e6 if int(usec) > 0 else None
            except ValueError:
                log.warning("WATCHDOG_USEC=%r is not a whole number; watchdog off", usec)
        self._sock: socket.socket | None = None
        self._failed = False
        self.dropped = 0

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, **fields: object) -> bool:
        """Send ``KEY=value`` lines, e.g. ``notify(READY=1, STATUS="ok")``; True when sent."""
        if self.address is None:
            return False
        payload = "\n".join(f"{k}={v}" for k, v in fields.items()).encode()
        addr = "\0" + self.address[1:] if self.address.startswith("@") else self.address
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(payload, socket.MSG_DONTWAIT, addr)
        except BlockingIOError:
            self.dropped += 1
            if self.dropped == 1:
                log.warning("sd_notify: %s is not being read; message dropped", self.address)
            return False
        except OSError as exc:
            if not self._failed:        # once: the socket does not come back by itself
                log.warning("sd_notify to %s failed: %s", self.address, exc)
            self._failed = True
            return False
        self._failed = False
        return True

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
