"""The kernel: what every Property Service, the gateway and the client SDK build on.

The backend interface (``backend``), the directory interface (``directory``), values
(``values``), errors (``errors``), the model and its codec (``model``, ``model_codec``),
property paths (``paths``), the conflating queue (``conflation``), shared upstream listens
(``sharing``), the class wrapper (``core``), the line-protocol codec (``line_protocol``) and
small helpers they share (``backoff``, ``eager``, ``worker_pool``). The kernel imports no
application (``services.apps``) and no device code (``services.device``).
"""
