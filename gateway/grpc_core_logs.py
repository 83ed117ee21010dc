"""The gRPC C core's own log lines: errors only, unless ``GRPC_VERBOSITY`` says otherwise.

grpcio (1.85) writes its core's messages through absl logging straight to stderr, past Python's
``logging``, and with ``GRPC_VERBOSITY`` unset it writes INFO lines too. Some of them are a
client's to cause at will: every connection that sends GOAWAY (``ENHANCE_YOUR_CALM``,
``ping_timeout``) adds ``I1129 ... chttp2_transport.cc:1403] ...: Got goaway [11] ...``, one line
a connection, outside the budget of :mod:`gateway.client_faults` (docs/security.md, "No client can
make the gateway log a traceback"). The core reads the variable when grpc is first imported, so
this module sets it before then: the command line imports it ahead of everything that imports
grpc. An operator who wants the core's INFO lines back sets ``GRPC_VERBOSITY=INFO`` (or ``DEBUG``)
in the environment, which wins.
"""

from __future__ import annotations

import os

#: The core's level when the environment names none (ERROR, WARNING, INFO, DEBUG, NONE).
DEFAULT_GRPC_VERBOSITY = "ERROR"

os.environ.setdefault("GRPC_VERBOSITY", DEFAULT_GRPC_VERBOSITY)

__all__ = ["DEFAULT_GRPC_VERBOSITY"]
