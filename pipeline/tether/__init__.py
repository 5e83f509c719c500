"""Tethered capture over USB (PTP with pyusb): Canon EOS and Nikon focus drive (Sec. 8).

Modules: ``codes`` (protocol numbers), ``ptp`` (container and dataset codec),
``transport`` (pyusb I/O, class requests), ``session`` (transactions, retries),
``clock`` (system or virtual time), ``base`` (the driver interface and its
errors), ``canon``/``nikon`` (vendor drivers), ``dispatch`` (driver for a
session), ``flows`` (stack and sweep capture), ``calibrate`` (step size from
magnification), ``emulated`` (an emulated camera as a pyusb backend, its
personalities, byte layouts and scene), ``capabilities`` (which bodies the
flows accept, from GetDeviceInfo), ``replay`` (recorded gphoto2 --debug traffic
as a pyusb backend).
"""
