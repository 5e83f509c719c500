"""A PTP session: OpenSession/CloseSession, GetDeviceInfo, transactions, retries.

One transaction is: command container -> optional data phase (either direction)
-> response container, all with the same transaction id (ISO 15740 Sec. 9).
Busy and not-ready responses are retried with exponential backoff; a timeout
cancels the transaction with the class request 0x64 and waits until the device
reports it is idle again, so the session stays usable.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from pipeline.errors import TetherError
from pipeline.tether.clock import SYSTEM_CLOCK
from pipeline.tether.codes import (
    OC,
    PTP_VENDOR_EXTENSION_IDS,
    RC,
    USB_VENDOR_IDS,
    ContainerType,
    operation_name,
    response_name,
)
from pipeline.tether.ptp import Container, DeviceInfo, ProtocolError
from pipeline.tether.transport import EndpointStalled, TransportTimeout, UsbTransport

log = logging.getLogger(__name__)

SESSION_ID = 1


class PtpError(TetherError):
    """The camera answered a transaction with a response code other than OK."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


class CameraBusy(PtpError):
    """The camera stayed busy through every retry."""


class UnsupportedCamera(TetherError):
    """GetDeviceInfo lacks operations a flow needs."""


@dataclass(frozen=True)
class Response:
    code: int
    params: tuple[int, ...]
    data: bytes


class PtpSession:
    """Transactions with one camera.

    Parameters
    ----------
    transport : UsbTransport
    retries : int
        How often a busy / not-ready response is retried.
    backoff_s, max_backoff_s : float
        First wait between retries (doubled each time, capped).
    clock : SystemClock or VirtualClock
        Times every wait (an emulated camera shares a virtual one with the host).
    """

    def __init__(
        self,
        transport: UsbTransport,
        *,
        retries: int = 8,
        backoff_s: float = 0.05,
        max_backoff_s: float = 1.0,
        clock=SYSTEM_CLOCK,
    ) -> None:
        self.transport = transport
        self.retries = retries
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self.clock = clock
        self.sleep = clock.sleep
        self.busy_codes: set[int] = {RC.DeviceBusy}
        self.device_info: DeviceInfo | None = None
        self.vendor: str | None = None
        self.is_open = False
        self.retried = 0  # busy / not-ready responses absorbed so far
        # operations a body performs but hides in GetDeviceInfo (filled from a per-body table)
        self.extra_operations: set[int] = set()
        self._tid = 0

    # --- session --------------------------------------------------------------------------

    def open(self) -> DeviceInfo:
        """GetDeviceInfo, then OpenSession (closing a stale session first if needed)."""
        info = DeviceInfo.from_bytes(self.transaction(OC.GetDeviceInfo, want_data=True).data)
        self.device_info = info
        self.vendor = PTP_VENDOR_EXTENSION_IDS.get(info.vendor_extension_id) or USB_VENDOR_IDS.get(
            self.transport.device.idVendor
        )
        self._tid = 0
        response = self.transaction(OC.OpenSession, (SESSION_ID,), check=False)
        if response.code == RC.SessionAlreadyOpened:
            self.transaction(OC.CloseSession)
            self._tid = 0
            response = self.transaction(OC.OpenSession, (SESSION_ID,), check=False)
        self.check(OC.OpenSession, response)
        self.is_open = True
        return info

    def close(self) -> None:
        """CloseSession (if open) and release the USB interface."""
        try:
            if self.is_open:
                self.transaction(OC.CloseSession)
        finally:
            self.is_open = False
            self.transport.close()

    def supports(self, opcode: int) -> bool:
        """GetDeviceInfo lists ``opcode`` (or it is a known hidden operation of this body)."""
        if opcode in self.extra_operations:
            return True
        return self.device_info is not None and opcode in self.device_info.operations

    def require(self, opcodes, purpose: str) -> None:
        """Raise :class:`UnsupportedCamera` naming every operation GetDeviceInfo lacks."""
        missing = [op for op in opcodes if not self.supports(op)]
        if missing:
            model = self.device_info.model if self.device_info else "camera"
            names = ", ".join(operation_name(op, self.vendor) for op in missing)
            raise UnsupportedCamera(f"{model} cannot {purpose}: it lacks {names}")

    # --- transactions ---------------------------------------------------------------------

    def transaction(
        self,
        code: int,
        params: tuple[int, ...] = (),
        *,
        data_out: bytes | None = None,
        want_data: bool = False,
        timeout_ms: int | None = None,
        check: bool = True,
        busy_ok: bool = True,
    ) -> Response:
        """Run one operation; retry busy responses; cancel on timeout.

        Parameters
        ----------
        code, params : int, tuple of int
            Operation code and up to five parameters.
        data_out : bytes, optional
            Payload of a host-to-device data phase.
        want_data : bool
            Expect a device-to-host data phase (an empty payload if the camera sends none).
        check : bool
            Raise :class:`PtpError` unless the response is OK.
        busy_ok : bool
            Retry busy / not-ready responses (else return or raise them at once).
        """
        delay = self.backoff_s
        for attempt in range(self.retries + 1):
            response = self._once(code, params, data_out, want_data, timeout_ms)
            if not (busy_ok and response.code in self.busy_codes) or attempt == self.retries:
                break
            self.retried += 1
            log.debug(
                "%s: %s, retrying in %.2f s", operation_name(code, self.vendor),
                response_name(response.code, self.vendor), delay,
            )
            self.sleep(delay)
            delay = min(2 * delay, self.max_backoff_s)
        if check:
            self.check(code, response)
        return response

    def check(self, code: int, response: Response) -> None:
        if response.code == RC.OK:
            return
        message = (
            f"{operation_name(code, self.vendor)} failed: "
            f"{response_name(response.code, self.vendor)}"
        )
        if response.code in self.busy_codes:
            raise CameraBusy(f"{message} after {self.retries} retries", response.code)
        raise PtpError(message, response.code)

    def _once(self, code, params, data_out, want_data, timeout_ms) -> Response:
        tid = self._next_tid(code)
        t = self.transport
        try:
            t.send(Container(ContainerType.COMMAND, code, tid, tuple(params)),
                   timeout_ms=timeout_ms)
            if data_out is not None:
                t.send(Container(ContainerType.DATA, code, tid, payload=data_out),
                       timeout_ms=timeout_ms)
            data = b""
            reply = t.receive(timeout_ms=timeout_ms)
            if reply.type == ContainerType.DATA:
                data = reply.payload
                reply = t.receive(timeout_ms=timeout_ms)
        except TransportTimeout as err:
            self._abort(tid)
            raise TransportTimeout(
                f"{operation_name(code, self.vendor)} timed out; the transaction was cancelled "
                "and the session is still open"
            ) from err
        except EndpointStalled as err:
            self._abort(tid)
            raise EndpointStalled(
                f"{operation_name(code, self.vendor)}: the camera stalled the transfer; "
                "the endpoints were cleared and the session is still open"
            ) from err
        if reply.type != ContainerType.RESPONSE or reply.transaction_id != tid:
            raise ProtocolError(
                f"{operation_name(code, self.vendor)}: expected the response to transaction "
                f"{tid}, got a {reply.type.name} container for transaction {reply.transaction_id}"
            )
        if want_data is False and data:
            log.debug("%s sent %d unexpected data bytes", operation_name(code), len(data))
        return Response(reply.code, reply.params, data)

    def _next_tid(self, code: int) -> int:
        if code in (OC.GetDeviceInfo, OC.OpenSession) and not self.is_open:
            return 0  # outside a session the transaction id is 0 (ISO 15740 9.3.1)
        self._tid = self._tid % 0xFFFFFFFE + 1
        return self._tid

    def _abort(self, tid: int) -> None:
        """Cancel ``tid`` (class request 0x64), wait until idle, clear stalled endpoints."""
        t = self.transport
        t.cancel(tid)
        delay = self.backoff_s
        for _ in range(self.retries + 1):
            status, stalled = t.device_status()
            if stalled:
                t.clear_halts(stalled)
            if status == RC.OK:
                return
            self.sleep(delay)
            delay = min(2 * delay, self.max_backoff_s)
        raise TetherError(
            f"camera stayed {response_name(status, self.vendor)} after cancelling transaction "
            f"{tid}; reset it (power cycle) and retry"
        )
