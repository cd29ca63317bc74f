"""The machines the log tests read and write: the layout tests' own."""

from ..canbus.conftest import three_units, wide_inputs  # noqa: F401  (fixtures)
