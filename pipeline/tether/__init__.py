"""Tethered capture over USB (PTP with pyusb): Canon EOS and Nikon focus drive (Sec. 8).

Modules: ``codes`` (protocol numbers), ``ptp`` (container and dataset codec),
``transport`` (pyusb I/O, class requests), ``session`` (transactions, retries),
``camera``/``canon``/``nikon`` (vendor drivers), ``flows`` (stack and sweep
capture), ``calibrate`` (step size from magnification), ``scene`` and
``emulator`` (an emulated camera as a pyusb backend).
"""
