"""An emulated Canon EOS / Nikon body as a pyusb backend, and the scene it photographs.

``device`` (the camera and the :class:`~usb.backend.IBackend`), ``personalities``
(camera models), ``layouts`` (the documented byte layouts it sends), ``scene``
(the rendered two-plane scene).
"""
