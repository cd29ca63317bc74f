"""The emulated sensors as a bus listener sees them: decoded position, diagnostic and
heartbeat frames per cylinder, and a text view of them (``monitor``, ``demo``)."""

from __future__ import annotations

from dataclasses import dataclass

import can

from ddh_vsensor.canbus.dbc import FrameCodec, message_name
from ddh_vsensor.config import Config
from ddh_vsensor.estimator.flags import flag_text

NMT_NAMES = {0: "boot-up", 4: "stopped", 5: "operational", 127: "pre-op"}


@dataclass
class Reading:
    position_mm: float | None = None
    speed_mm_s: float | None = None
    status: int = 0
    position_t: float | None = None
    positions: int = 0
    uncertainty_mm: float | None = None
    flags: int = 0
    input_frames: int = 0
    rejected_frames: int = 0
    diag_t: float | None = None
    nmt_state: int | None = None
    heartbeat_t: float | None = None


class OutputWatcher:
    """``feed(msg)`` every frame; ``readings[actuator]`` holds the latest of each kind."""

    def __init__(self, cfg: Config, codec: FrameCodec | None = None) -> None:
        self.cfg = cfg
        self.codec = codec or FrameCodec(cfg)
        self._kinds: dict[int, tuple[str, str]] = {}
        for actuator, unit in cfg.can.units.items():
            self._kinds[self.codec.ids[message_name("position", actuator)]] = ("position",
                                                                              actuator)
            self._kinds[self.codec.ids[message_name("diag", actuator)]] = ("diag", actuator)
            self._kinds[0x700 + unit.sensor_node_id] = ("heartbeat", actuator)
        self.readings = {a: Reading() for a in cfg.can.units}
        self.frames = 0

    @property
    def ids(self) -> list[int]:
        return sorted(self._kinds)

    def feed(self, msg: can.Message) -> tuple[str, str] | None:
        """(kind, actuator) of a frame of the emulated sensors, None for any other."""
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            return None
        kind = self._kinds.get(msg.arbitration_id)
        if kind is None:
            return None
        what, actuator = kind
        r = self.readings[actuator]
        if what == "heartbeat":
            if len(msg.data) < 1:
                return None
            r.nmt_state, r.heartbeat_t = msg.data[0] & 0x7F, msg.timestamp
        else:
            try:
                decoded = self.codec.decode(msg)
            except Exception:   # noqa: BLE001 - a watcher shows what it can
                return None
            if decoded is None:
                return None
            s = decoded[1]
            if what == "position":
                r.position_mm, r.speed_mm_s = s["Position"], s["Speed"]
                r.status, r.position_t = int(s["Status"]), msg.timestamp
                r.positions += 1
            else:
                r.uncertainty_mm, r.flags = s["Uncertainty"], int(s["Flags"])
                r.input_frames, r.rejected_frames = int(s["InputFrames"]), int(s["RejectedFrames"])
                r.diag_t = msg.timestamp
        self.frames += 1
        return kind

    def lines(self, truth_mm: dict[str, float] | None = None) -> list[str]:
        """One line per cylinder: position, speed, uncertainty, flags (and truth, error)."""
        out = []
        for actuator, r in self.readings.items():
            if r.position_mm is None:
                out.append(f"{actuator:<7} (no position frame yet)")
                continue
            text = f"{actuator:<7} {r.position_mm:9.2f} mm {r.speed_mm_s:8.1f} mm/s"
            if r.uncertainty_mm is not None:
                text += f"  +-{r.uncertainty_mm:6.2f} mm"
            if truth_mm is not None and actuator in truth_mm:
                err = r.position_mm - truth_mm[actuator]
                text += f"  true {truth_mm[actuator]:8.2f} mm  error {err:+7.2f} mm"
            text += f"  [{flag_text(r.status)}]"
            if r.diag_t is not None:
                text += f"  in {r.input_frames} rej {r.rejected_frames}"
            if r.nmt_state is not None:
                text += f"  {NMT_NAMES.get(r.nmt_state, r.nmt_state)}"
            out.append(text)
        return out
