"""PTP numbers: container types, operation/response/event codes, class requests.

The one table of protocol numbers (PIMA 15740 / ISO 15740 and the USB Still
Image Capture Device class). Vendor extensions are kept in separate enums
because their numbers collide (e.g. event 0xC101 is Canon EOS RequestGetEvent
but Nikon ObjectAddedInSDRAM; response 0xA001 is Canon UnknownCommand but
Nikon HardwareError): always look vendor codes up through the vendor's enum.
Names follow libgphoto2's ``camlibs/ptp2/ptp.h`` (``PTP_OC_*``, ``PTP_RC_*``,
``PTP_EC_*``, ``PTP_DPC_*``).
"""

from __future__ import annotations

from enum import IntEnum

STILL_IMAGE_CLASS = (6, 1, 1)  # bInterfaceClass, SubClass, Protocol (USB Still Image)

USB_VENDOR_IDS = {0x04A9: "canon", 0x04B0: "nikon"}
PTP_VENDOR_EXTENSION_IDS = {0x0000000B: "canon", 0x0000000A: "nikon"}  # PTP_VENDOR_CANON/NIKON


class ContainerType(IntEnum):
    COMMAND = 1
    DATA = 2
    RESPONSE = 3
    EVENT = 4


class ClassRequest(IntEnum):
    """USB Still Image class-specific control requests (bRequest)."""

    CANCEL = 0x64
    GET_EXTENDED_EVENT_DATA = 0x65
    DEVICE_RESET = 0x66
    GET_DEVICE_STATUS = 0x67


class OC(IntEnum):
    """Standard operation codes (PTP_OC_*)."""

    GetDeviceInfo = 0x1001
    OpenSession = 0x1002
    CloseSession = 0x1003
    GetObjectInfo = 0x1008
    GetObject = 0x1009
    DeleteObject = 0x100B
    InitiateCapture = 0x100E
    GetDevicePropValue = 0x1015
    SetDevicePropValue = 0x1016
    GetPartialObject = 0x101B


class CanonOC(IntEnum):
    """Canon EOS operation codes (PTP_OC_CANON_EOS_*)."""

    GetPartialObject = 0x9107
    RemoteRelease = 0x910F
    SetDevicePropValueEx = 0x9110
    SetRemoteMode = 0x9114
    SetEventMode = 0x9115
    GetEvent = 0x9116
    TransferComplete = 0x9117
    BulbStart = 0x9125
    BulbEnd = 0x9126
    RemoteReleaseOn = 0x9128
    RemoteReleaseOff = 0x9129
    DriveLens = 0x9155


class NikonOC(IntEnum):
    """Nikon operation codes (PTP_OC_NIKON_*)."""

    InitiateCaptureRecInSdram = 0x90C0
    ChangeCameraMode = 0x90C2
    GetEvent = 0x90C7  # "CheckEvent" in older headers
    DeviceReady = 0x90C8
    StartLiveView = 0x9201
    EndLiveView = 0x9202
    MfDrive = 0x9204
    InitiateCaptureRecInMedia = 0x9207
    TerminateCapture = 0x920C


class RC(IntEnum):
    """Standard response codes (PTP_RC_*)."""

    OK = 0x2001
    GeneralError = 0x2002
    SessionNotOpen = 0x2003
    InvalidTransactionID = 0x2004
    OperationNotSupported = 0x2005
    ParameterNotSupported = 0x2006
    IncompleteTransfer = 0x2007
    InvalidObjectHandle = 0x2009
    DeviceBusy = 0x2019
    InvalidParameter = 0x201D
    SessionAlreadyOpened = 0x201E
    TransactionCancelled = 0x201F


class CanonRC(IntEnum):
    """Canon EOS response codes (PTP_RC_CANON_EOS_*)."""

    UnknownCommand = 0xA001
    OperationRefused = 0xA005
    LensCoverClosed = 0xA006
    LowBattery = 0xA101
    ObjectNotReady = 0xA102
    CannotMakeObject = 0xA104
    MemoryStatusNotReady = 0xA106


class NikonRC(IntEnum):
    """Nikon response codes (PTP_RC_NIKON_*)."""

    HardwareError = 0xA001
    OutOfFocus = 0xA002
    ChangeCameraModeFailed = 0xA003
    InvalidStatus = 0xA004
    NotLiveView = 0xA00B
    MfDriveStepEnd = 0xA00C
    MfDriveStepInsufficiency = 0xA00E
    BulbReleaseBusy = 0xA200


class EC(IntEnum):
    """Standard event codes (PTP_EC_*)."""

    CancelTransaction = 0x4001
    ObjectAdded = 0x4002
    DevicePropChanged = 0x4006
    CaptureComplete = 0x400D


class CanonEC(IntEnum):
    """Canon EOS event record types inside GetEvent data (PTP_EC_CANON_EOS_*)."""

    RequestGetEvent = 0xC101
    ObjectAddedEx = 0xC181
    RequestObjectTransfer = 0xC186
    PropValueChanged = 0xC189
    AvailListChanged = 0xC18A
    CameraStatusChanged = 0xC18B
    ObjectAddedEx64 = 0xC1A7


class NikonEC(IntEnum):
    """Nikon event codes (PTP_EC_Nikon_*)."""

    ObjectAddedInSDRAM = 0xC101
    CaptureCompleteRecInSdram = 0xC102


class CanonDPC(IntEnum):
    """Canon EOS device properties (PTP_DPC_CANON_EOS_*)."""

    FocusMode = 0xD108
    Owner = 0xD115  # string
    CaptureDestination = 0xD11C
    SerialNumber = 0xD1AF  # string
    EVFOutputDevice = 0xD1B0
    EVFMode = 0xD1B1
    Artist = 0xD1D0  # string
    Copyright = 0xD1D1  # string
    LensName = 0xD1D8  # string


# Canon EOS properties whose values are NUL-terminated ASCII strings (libgphoto2 ``ptp.c``)
CANON_STRING_PROPERTIES = frozenset({CanonDPC.Owner, CanonDPC.SerialNumber, CanonDPC.Artist,
                                     CanonDPC.Copyright, CanonDPC.LensName})


class NikonDPC(IntEnum):
    """Nikon device properties (PTP_DPC_NIKON_*)."""

    LiveViewStatus = 0xD1A2
    LiveViewProhibitCondition = 0xD1A4


OBJECT_FORMAT_ASSOCIATION = 0x3001  # a folder (ISO 15740 ObjectFormatCode)
CANON_FOCUS_MODE_MF = 3  # FocusMode (0xD108) with the lens switch at MF
CANON_DEST_CARD, CANON_DEST_PC = 2, 4  # CaptureDestination (0xD11C): card, PC (SDRAM)
CANON_REMOTE_MODE, CANON_REMOTE_MODE_EOS_M = 1, 0x15  # SetRemoteMode parameter


CANON_EVF_OFF, CANON_EVF_TFT, CANON_EVF_PC = 0, 1, 2  # EVFOutputDevice values
CANON_DRIVE_FAR = 0x8000  # DriveLens parameter: 0x0001-0x0003 near, 0x8001-0x8003 far
NIKON_MFDRIVE_NEAR, NIKON_MFDRIVE_FAR = 1, 2  # MfDrive first parameter (direction)
NIKON_SDRAM_HANDLE = 0xFFFF0001  # object handle of an image captured into SDRAM
NIKON_NO_AF = 0xFFFFFFFF  # InitiateCaptureRecInSdram parameter: no AF before capture

_VENDOR_OPS = {"canon": CanonOC, "nikon": NikonOC}
_VENDOR_RCS = {"canon": CanonRC, "nikon": NikonRC}


def operation_name(code: int, vendor: str | None = None) -> str:
    """``"Name (0x1234)"`` of an operation code, resolved in the vendor's table."""
    return _name(code, OC, _VENDOR_OPS.get(vendor or ""))


def response_name(code: int, vendor: str | None = None) -> str:
    """``"Name (0x2019)"`` of a response code, resolved in the vendor's table."""
    return _name(code, RC, _VENDOR_RCS.get(vendor or ""))


def _name(code: int, standard: type[IntEnum], vendor: type[IntEnum] | None) -> str:
    for table in (standard, vendor):
        if table is not None and code in table._value2member_map_:
            return f"{table(code).name} (0x{code:04X})"
    return f"0x{code:04X}"
