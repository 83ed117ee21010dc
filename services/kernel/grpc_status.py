"""The one table between the project's error codes and gRPC's status codes.

``Code`` numbers are gRPC's numbers, so the table pairs each code with the status of the same
number. The gateway's gRPC front answers with it and the client SDK reads answers with it; both
take it from here, so the two sides cannot drift.
"""

from __future__ import annotations

from typing import Final

import grpc

from services.kernel.errors import Code

__all__ = ["CODE_OF_STATUS", "GRPC_STATUS"]

#: Code → grpc.StatusCode of the same number.
GRPC_STATUS: Final[dict[Code, grpc.StatusCode]] = {
    code: status for status in grpc.StatusCode for code in Code if status.value[0] == code.value
}

assert len(GRPC_STATUS) == len(Code), "every Code has a gRPC status of the same number"

#: grpc.StatusCode → Code, the reverse of :data:`GRPC_STATUS`.
CODE_OF_STATUS: Final[dict[grpc.StatusCode, Code]] = {status: code for code, status in GRPC_STATUS.items()}
