"""Which URLs a Set on ``services.<name>`` may register."""

from __future__ import annotations

from urllib.parse import urlsplit

from services.kernel.errors import InvalidArgument
from services.kernel.paths import validate_service_name

__all__ = ["REGISTRABLE_SCHEMES", "check_url"]

#: URL schemes a Set on ``services.<name>`` may register (``local`` services come from the config).
REGISTRABLE_SCHEMES = ("tcp", "serial", "grpc")


def check_url(url: str) -> str:
    """Return ``url`` when a Set may register it, else raise InvalidArgument saying what is wrong."""
    shown = repr(url[:120])
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as e:
        raise InvalidArgument(f"malformed URL {shown}: {e}") from None
    if parts.scheme == "local" or url == "local":
        raise InvalidArgument("in-process (local) services come from the gateway's config; register a URL")
    if parts.scheme not in REGISTRABLE_SCHEMES:
        known = ", ".join(f"{s}://" for s in REGISTRABLE_SCHEMES)
        raise InvalidArgument(f"malformed URL {shown}: expected one of {known}")
    if any(c.isspace() for c in url):
        raise InvalidArgument(f"malformed URL {shown}: it contains whitespace")
    if parts.scheme == "serial":
        if not parts.path or parts.path == "/":
            raise InvalidArgument(f"malformed URL {shown}: expected serial:///dev/ttyUSB0?baudrate=115200")
        return url
    if not parts.hostname or port is None or port == 0:
        raise InvalidArgument(
            f"malformed URL {shown}: expected {parts.scheme}://host:port with a port 1-65535"
        )
    if parts.path not in ("", "/"):
        if parts.scheme == "grpc":
            # grpc://host:port/SERVICE names the service on the other gateway.
            try:
                validate_service_name(parts.path[1:])
            except InvalidArgument as e:
                expected = "grpc://host:port or grpc://host:port/SERVICE"
                raise InvalidArgument(f"malformed URL {shown}: expected {expected}: {e.message}") from None
            return url
        raise InvalidArgument(f"malformed URL {shown}: expected {parts.scheme}://host:port with no path")
    return url
