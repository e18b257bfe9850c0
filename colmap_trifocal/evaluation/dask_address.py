"""``--dask ADDRESS``: checked, and its scheduler seen to speak Dask, before a client connects.

Dask's client reads the first 8 bytes a server sends as the length of its first message
and allocates that much: pointed at a web server, whose answer starts ``HTTP/1.``, it asks
for exbibytes. An empty address, another scheme (``http://``, ``inproc://``) or a
malformed host raise ``ValueError`` deep inside Dask. So the address is parsed here (the
``tcp://`` scheme, or none, with a host and a port; ``tls://`` is left to Dask's own
configuration), and a ``tcp`` scheduler is probed first: a Dask scheduler sends its
handshake as soon as a connection is accepted, so the probe connects, reads that
message's 8-byte length without sending anything, and checks it is a small positive
number. Each step is bounded by :data:`PROBE_TIMEOUT_S`.
"""

from __future__ import annotations

import re
import socket
import struct

from ..common.errors import CalibrationError

#: Seconds to connect to the scheduler, and then for its first bytes.
PROBE_TIMEOUT_S = 10.0
#: The largest first message (its handshake) a Dask scheduler is taken to send.
MAX_HANDSHAKE_BYTES = 1 << 20
#: Schemes the command line takes: ``tcp`` is probed, ``tls`` needs Dask's own settings.
SCHEMES = ("tcp", "tls")

_HOST_PORT = re.compile(
    r"^(?:\[(?P<ipv6>[0-9A-Fa-f:.]+)\]|(?P<host>[A-Za-z0-9._-]+)):(?P<port>\d+)$"
)


def parse_dask_address(address: str) -> tuple[str, str, int]:
    """``(scheme, host, port)`` of ``ADDRESS`` (``tcp://host:8786``, ``host:8786``,
    ``tcp://[::1]:8786``, ``tls://host:8786``).

    Raises:
        CalibrationError: empty, another scheme, no host or port, a port out of range.
    """
    scheme, _, rest = address.rpartition("://") if "://" in address else ("tcp", "", address)
    if scheme not in SCHEMES:
        raise CalibrationError(
            f"--dask {address!r}: the scheme must be one of {', '.join(SCHEMES)} "
            "(e.g. tcp://scheduler:8786)"
        )
    match = _HOST_PORT.fullmatch(rest)
    if match is None:
        raise CalibrationError(
            f"--dask {address!r}: expected HOST:PORT (e.g. tcp://scheduler:8786, tcp://[::1]:8786)"
        )
    port = int(match["port"])
    if not 1 <= port <= 65535:
        raise CalibrationError(f"--dask {address!r}: port {port} is not in [1, 65535]")
    return scheme, match["ipv6"] or match["host"], port


def check_dask_address(address: str) -> str:
    """Check ``ADDRESS`` and, for ``tcp``, that a Dask scheduler answers there; returns the
    address as given.

    Raises:
        CalibrationError: a malformed address, nothing listening, or a server that is not
            a Dask scheduler (it sends nothing, or not a Dask message).
    """
    scheme, host, port = parse_dask_address(address)
    if scheme == "tcp":
        first = _first_bytes(address, host, port)
        (length,) = struct.unpack("<Q", first)
        if not 0 < length <= MAX_HANDSHAKE_BYTES:
            raise CalibrationError(
                f"--dask {address}: the server there is not a Dask scheduler (its first "
                f"bytes {first!r} are no Dask message)"
            )
    return address


def _first_bytes(address: str, host: str, port: int) -> bytes:
    """The first 8 bytes the server at ``host:port`` sends unasked."""
    try:
        with socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S) as connection:
            data = b""
            while len(data) < 8:
                chunk = connection.recv(8 - len(data))
                if not chunk:
                    break
                data += chunk
    except TimeoutError:
        raise CalibrationError(
            f"--dask {address}: no Dask scheduler answered within {PROBE_TIMEOUT_S:g} s "
            "(the server there sends nothing, or nothing listens)"
        ) from None
    except OSError as exc:
        raise CalibrationError(
            f"cannot connect to the Dask scheduler {address}: {exc.strerror or exc}"
        ) from None
    if len(data) < 8:
        raise CalibrationError(
            f"--dask {address}: the server there closed the connection: not a Dask scheduler"
        )
    return data
