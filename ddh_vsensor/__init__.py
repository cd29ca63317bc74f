"""ddh-vsensor: a virtual position sensor for pump-controlled (DDH) hydraulic cylinders."""

__version__ = "0.1.0"
