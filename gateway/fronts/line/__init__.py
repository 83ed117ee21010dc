"""The line front: devices and clients that dial in and speak the line protocol over TCP.

* :mod:`~gateway.fronts.line.listener` — the listener: a client's requests go to the engine in
  its plain types; a peer that greets is a device registering itself.
* :mod:`~gateway.fronts.line.inbound` — a dialled-in device served through the line-protocol proxy.
"""
