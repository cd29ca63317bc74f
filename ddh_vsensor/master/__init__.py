"""The master's side of the emulated sensors, for the CLI, the benches and the tests: an SDO/NMT
client (:mod:`.client`), the sensors' frames as a listener sees them (:mod:`.watch`), and timed
replay of a CAN log onto a bus (:mod:`.replay`)."""
