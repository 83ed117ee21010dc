"""The device conformance kit: docs/device-spec.md, clause by clause, against a real device.

``psgateway device-check URL`` (:mod:`gateway.device_check_cli`) runs it; tests call
:func:`check_device` and read the :class:`Report`. The kit is a client of the line protocol
built on the project's one codec (``services.kernel.line_protocol``).
"""

from gateway.conformance.clauses import CLAUSES, Clause
from gateway.conformance.runner import FAIL, PASS, SKIP, Outcome, Report, check_device

__all__ = ["CLAUSES", "FAIL", "PASS", "SKIP", "Clause", "Outcome", "Report", "check_device"]
