"""One error hierarchy for everything that talks to devices (python-can style).

Vendor and OS errors are re-raised ``from`` the original so the cause stays visible; messages name the
device and the port, so a user knows what to check.
"""

from __future__ import annotations

from models.errors import VslabError


class AcquisitionError(VslabError):
    """Base of the acquisition layer's errors: devices, codecs, schemas, sessions, plans, safety."""


class CodecError(AcquisitionError, ValueError):
    """Bytes that a wire codec cannot decode (a bad checksum, a malformed frame or line)."""


class DeviceError(AcquisitionError):
    """Base of every device error."""


class DeviceNotFoundError(DeviceError):
    """The port does not exist or nothing answers on it (unplugged, wrong port, wrong ID)."""


class DeviceTimeoutError(DeviceError):
    """The device did not answer in time (after the retries)."""


class DeviceProtocolError(DeviceError):
    """A reply was malformed or failed its checksum (after the retries)."""


class DeviceReplyError(DeviceError):
    """The device answered, with an error status."""


class DeviceDisconnectedError(DeviceError):
    """The device went away while open (I/O error on the port)."""
