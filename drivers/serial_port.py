"""The serial port of the encoder link: opened exclusively, each failure named.

The errors here are the link's: every one names the problem and the port, so that the
service's status and log say what an operator can fix (a cable, a permission, another
process holding the port).
"""

from __future__ import annotations

import errno
import os
import stat

import serial

__all__ = ["LinkError", "PortNotFoundError", "PortBusyError", "PortPermissionError",
           "WrongDeviceError", "ProtocolVersionError", "NoAnswerError", "DeviceRejectedError",
           "DeviceLostError", "open_port"]


class LinkError(RuntimeError):
    """A problem with the encoder link; the message names it and the port."""


class PortNotFoundError(LinkError):
    pass


class PortBusyError(LinkError):
    pass


class PortPermissionError(LinkError):
    pass


class WrongDeviceError(LinkError):
    pass


class ProtocolVersionError(LinkError):
    pass


class NoAnswerError(LinkError):
    pass


class DeviceRejectedError(LinkError):
    pass


class DeviceLostError(LinkError):
    """The device vanished or fell silent during a session."""


def open_port(port: str, baudrate: int, timeout: float) -> serial.Serial:
    """Open ``port`` exclusively, raising a LinkError that names what went wrong."""
    try:
        mode = os.stat(port).st_mode
    except FileNotFoundError:
        raise PortNotFoundError(f"serial port {port} does not exist (device unplugged or wrong "
                                "path)") from None
    except PermissionError:
        raise PortPermissionError(f"permission denied looking up serial port {port}") from None
    if not stat.S_ISCHR(mode):
        raise WrongDeviceError(f"{port} is not a serial device (not a character device)")
    ser = serial.Serial()
    ser.port, ser.baudrate, ser.timeout, ser.write_timeout = port, baudrate, timeout, 0.2
    ser.exclusive = True
    try:
        ser.open()
    except serial.SerialException as exc:
        code = exc.errno
        if code in (errno.EACCES, errno.EPERM):
            raise PortPermissionError(f"permission denied opening serial port {port}: the service "
                                      "user needs read/write access (e.g. membership of the "
                                      "'dialout' group)") from None
        if code in (errno.EAGAIN, errno.EBUSY):
            raise PortBusyError(f"serial port {port} is busy: another process holds it open") from None
        if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
            raise PortNotFoundError(f"serial port {port} vanished while opening ({exc})") from None
        if code is None:  # pyserial could not apply terminal settings: not a tty
            raise WrongDeviceError(f"{port} is not a serial port ({exc})") from None
        raise LinkError(f"cannot open serial port {port}: {exc}") from None
    return ser
