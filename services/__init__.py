"""Property Services in Python, in three rooms.

* :mod:`services.kernel`: what every service and the gateway build on (the backend interface,
  values, errors, the model, conflation, shared listens, the class wrapper, the line codec).
* :mod:`services.apps`: the system services (registry with licences and scheduler, groups,
  state machines, storage, vision, environment model, simulators); each builds on the kernel.
* :mod:`services.device`: the device side of the line protocol (and the C library in ``c/``).
"""
