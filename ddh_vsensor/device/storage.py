"""Parameters a master stores with 0x1010 and restores to their defaults with 0x1011 (CiA 301),
kept per sensor node in one small file beside the service's state files.

Sub-index 1 covers all parameters: the communication area's settings (0x1000..0x1FFF: PDO
COB-IDs, transmission types, inhibit and event timers, mappings, EMCY COB-ID and inhibit time,
guard time and life time factor, consumer and producer heartbeat times) and the profile's
(0x6000..0x9FFF: operating parameters, work area limits); sub-index 2 the communication
area's only. What is not a parameter is never stored: the error field 0x1003, the store and
restore commands themselves, the preset 0x6010 (a command that moves the estimate) and the
cyclic timer 0x6200 (TPDO1's event timer under another name, stored as 0x1800 sub 5).

The file, ``<state dir>/<unit>.parameters.json``, written atomically::

    {"format": "ddh-vsensor stored parameters 1", "node_id": 49,
     "parameters": {"0x1017.0": 500, "0x1800.5": 20, ...}}

values as the object's integer; a file of another node ID (the configuration moved the node)
or that does not parse is ignored with a warning, and the defaults apply.

A store is written before the SDO response confirms it (CiA 301: the response says it is
stored), in the service's loop: one atomic write with its fsyncs, 13 ms median and 24 ms at
most on this machine's disk, a tick or two of delay while a master commissions the node.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator, Mapping
from pathlib import Path

import canopen

from ddh_vsensor.atomic import atomic_write, remove_temp_files

log = logging.getLogger(__name__)

SAVE = 0x65766173                   # "save", little-endian ASCII (CiA 301 0x1010)
LOAD = 0x64616F6C                   # "load" (0x1011)
ALL, COMMUNICATION = 1, 2           # sub-indices of 0x1010 and 0x1011
COMMUNICATION_AREA = range(0x1000, 0x2000)
APPLICATION_AREA = range(0x6000, 0xA000)
NOT_PARAMETERS = frozenset({0x1003, 0x1010, 0x1011, 0x6010, 0x6200})
FORMAT = "ddh-vsensor stored parameters 1"
MAX_FILE_BYTES = 65536

Key = tuple[int, int]               # (index, subindex)


def in_scope(index: int, sub: int) -> bool:
    """Whether object ``index`` is stored by 0x1010 sub ``sub`` (1 all, 2 communication)."""
    if index in NOT_PARAMETERS:
        return False
    return index in COMMUNICATION_AREA or (sub == ALL and index in APPLICATION_AREA)


def parameters(od: canopen.ObjectDictionary, sub: int) -> Iterator[canopen.objectdictionary.ODVariable]:
    """Every writable integer variable of ``od`` that 0x1010 sub ``sub`` stores."""
    for obj in od.values():
        if not in_scope(obj.index, sub):
            continue
        variables = [obj] if isinstance(obj, canopen.objectdictionary.ODVariable) \
            else list(obj.values())
        for var in variables:
            if var.writable and var.data_type in canopen.objectdictionary.INTEGER_TYPES:
                yield var


class ParameterStore:
    """One node's stored parameters on disk."""

    def __init__(self, path: Path, node_id: int) -> None:
        self.path, self.node_id = Path(path), node_id

    def load(self) -> dict[Key, int]:
        """The stored values (empty: nothing stored, or a file that cannot be used)."""
        for tmp in remove_temp_files(self.path):
            log.info("removed %s, left by an interrupted store", tmp.name)
        try:
            with open(self.path, "rb") as fh:
                raw = fh.read(MAX_FILE_BYTES + 1)
        except FileNotFoundError:
            return {}
        except OSError as exc:
            log.warning("%s: cannot read the stored parameters (%s); defaults apply",
                        self.path, exc.strerror or exc)
            return {}
        try:
            if len(raw) > MAX_FILE_BYTES:
                raise ValueError(f"longer than {MAX_FILE_BYTES} bytes")
            data = json.loads(raw)
            if data.get("format") != FORMAT:
                raise ValueError(f"not {FORMAT!r}")
            if data.get("node_id") != self.node_id:
                raise ValueError(f"stored for node {data.get('node_id')}, this is node "
                                 f"{self.node_id}")
            values = {}
            for key, value in data["parameters"].items():
                index, sub = key.split(".")
                if isinstance(value, bool) or not isinstance(value, int):
                    raise TypeError(f"{key}: not an integer")
                values[(int(index, 16), int(sub))] = value
            return values
        except (ValueError, KeyError, AttributeError, TypeError) as exc:
            log.warning("%s: stored parameters ignored (%s); defaults apply", self.path, exc)
            return {}

    def save(self, values: Mapping[Key, int]) -> None:
        """Replace the file with ``values`` (none: the file is removed); raises OSError."""
        if not values:
            self.path.unlink(missing_ok=True)
            return
        data = {"format": FORMAT, "node_id": self.node_id,
                "parameters": {f"0x{index:04X}.{sub}": value
                               for (index, sub), value in sorted(values.items())}}
        with atomic_write(self.path) as fh:
            json.dump(data, fh, indent=1)
            fh.write("\n")
