"""Compatibility names: the driver interface is in :mod:`pipeline.tether.base`, dispatch in
:mod:`pipeline.tether.dispatch` (kept for imports written before the split; remove once unused).
"""

from pipeline.tether.base import CapturedObject, DriveRefused, EndStop, FocusCamera
from pipeline.tether.dispatch import camera_for

__all__ = ["CapturedObject", "DriveRefused", "EndStop", "FocusCamera", "camera_for"]
