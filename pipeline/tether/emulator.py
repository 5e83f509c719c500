"""Compatibility names: the emulator moved to :mod:`pipeline.tether.emulated` (remove later)."""

from pipeline.tether.emulated.device import (
    CANON,
    NIKON,
    EmulatedBackend,
    EmulatedCamera,
    Faults,
    OtherDevice,
    Personality,
    emulated_backend,
)

__all__ = ["CANON", "NIKON", "EmulatedBackend", "EmulatedCamera", "Faults", "OtherDevice",
           "Personality", "emulated_backend"]
