"""The Sevcon TPDO1's precompiled decoder gives what cantools decodes, on every machine."""

from __future__ import annotations

import random
import struct
from pathlib import Path

import pytest

from ddh_vsensor.canbus import FrameCodec, message_name
from ddh_vsensor.config import load_config

CONFIGS = sorted((Path(__file__).resolve().parents[2] / "config").glob("*.yaml"))


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_sevcon_decoder_equals_cantools(path: Path) -> None:
    cfg = load_config(path)
    codec = FrameCodec(cfg)
    rng = random.Random(11)
    for unit in cfg.unit_names:
        decode = codec.sevcon_decoder(unit)
        length = codec.messages[message_name("sevcon", unit)].length
        frames = [bytes(rng.getrandbits(8) for _ in range(length)) for _ in range(2000)]
        frames += [bytes(length), b"\xff" * length, b"\x00\x80" + b"\x00\x00\x00\x80"]
        for data in frames:
            signals = codec.messages[message_name("sevcon", unit)].decode(
                data, decode_choices=False)
            torque, speed = decode(data)
            assert (torque, speed) == (signals["TorqueActual"], signals["VelocityActual"])
            assert type(torque) is type(signals["TorqueActual"])
            assert type(speed) is type(signals["VelocityActual"])


def test_sevcon_decoder_refuses_other_lengths() -> None:
    cfg = load_config(None)
    decode = FrameCodec(cfg).sevcon_decoder(cfg.unit_names[0])
    for data in (b"", bytes(5), bytes(7)):
        with pytest.raises(struct.error):
            decode(data)
