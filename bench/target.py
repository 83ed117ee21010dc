"""Names of the service and properties every part of the benchmark reads, writes and listens to.

Both servers offer them: the bare server creates a property on its first Set;
the gateway serves :class:`bench.gateway_server.BenchTarget` under ``SERVICE``.
"""

from __future__ import annotations

SERVICE = "bench"
#: The one property of parts (a), (b), (c) and (d).
VALUE_PROPERTY = "value"
#: The properties of the batched Listen part: one burst of Sets touches each once.
BATCH_PROPERTIES = tuple(f"v{i}" for i in range(10))
