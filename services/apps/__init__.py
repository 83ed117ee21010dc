"""The applications: the system services, each built on the kernel (``services.kernel``).

The registry with licences and scheduler (``registry``), groups (``group``, ``formations``,
``query``, ``location_following``), state machines (``statemachine``), storage (``storage``),
vision (``vision``), the environment model (``environment``), the simulators (``simulators``,
``temperature_field``) and the catalog of kinds a configuration creates by name (``catalog``).
"""
