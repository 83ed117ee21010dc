"""The resource service: which services exist, how to reach them, whether they are alive.

``services`` lists the known service names; ``services.<name>`` is the
contact URL and ``services.<name>.type``, ``.url``, ``.state``,
``.last_seen``, ``.misses``, ``.lease`` and ``.location`` tell more. A Listen
on ``services`` hears every join and leave, one on ``services.*.state``
every change of state.

Served by :class:`RegistryService` (a LocalService that also takes Sets on
``services.<name>``), the registry changes the set of services itself,
through the :class:`~services.kernel.directory.Directory` it is given:

* **Register**: Set ``services.<name>`` to ``tcp://host:port``,
  ``serial:///dev/ttyUSB0?baudrate=115200`` or ``grpc://host:port`` (request
  parameters: ``type`` to declare the resource type, ``lease`` in seconds).
  The backend is created and must answer a Get of ``properties`` within
  ``register_timeout``; otherwise nothing is registered.
* **Unregister**: Set ``services.<name>`` to the empty value.
* **Liveness**: every ``period`` seconds each service that is not in-process
  is checked (``Backend.check``: a Get of ``properties``, or less for a
  line-protocol device) under ``timeout``; after ``misses`` misses in a
  row it is ``down``, and a registered one (not from the config) is removed
  after ``grace`` seconds down. A service with a lease is not polled: it Sets
  ``services.<name>.lease`` to renew it, and is ``down`` when it lapses.
* **Search**: Get ``find`` with parameters ``type``, ``near``, ``radius``,
  ``state``, ``limit``, ``where`` (see :mod:`services.apps.query`).

The gateway's router keeps the plain methods :meth:`Registry.add`,
:meth:`Registry.remove` and :meth:`Registry.set_state` working as before; with
a directory, the registry also follows joins and leaves by itself.

Every registration URL is checked against ``allow`` (an :class:`AllowList`:
networks and ports, serial path globs; default loopback only) before any
connection is made; a URL naming the gateway itself is a loop and refused.
Configured services cannot be unregistered from outside, reserved names
cannot be taken, and at most ``max_registrations`` registrations are held.

**Service states** (the SOA layer): ``services.<name>.availability`` is
``death`` (down), ``dormant`` (declared, not running: :meth:`Registry.wake`
starts it), ``ready`` or ``active`` (a licence is held on it,
``services.<name>.licence``). ``state`` keeps its meaning (up, down, connecting).

**Licences**: exclusive use of a service or a subtree for a while
(:mod:`services.apps.registry.licences`): actions ``acquire`` (parameters
``service``, ``duration``, ``subtree``; answers the licence id), ``renew``
(``licence``, ``duration``), ``release`` (``licence``); ``licences`` lists
the ids held, ``licences.<id>`` is a marker a Listen follows. A licence's
deadline is a :class:`Lease`, the same as a registered service's lease.

Modules: ``lease`` (the deadline both share), ``licences`` (the licences),
``urls`` (which URLs may be registered), ``allow`` (which addresses), ``entry`` (one service's
row, its state and lease), ``table`` (the rows and the search index),
``registration`` (register and unregister through the directory),
``liveness`` (checks, down, removal after ``grace``), ``persistence`` (the
registrations file), ``service`` (:class:`Registry` and
:class:`RegistryService`). Locations are followed by
:class:`services.apps.location_following.LocationFollower`.
"""

from services.apps.registry.allow import DEFAULT_ALLOW, AllowList, parse_allow_entry
from services.apps.registry.entry import AVAILABILITIES, STATES, ServiceEntry, ServiceList
from services.apps.registry.lease import Lease
from services.apps.registry.licences import (
    DEFAULT_LICENCE_DURATION,
    DEFAULT_MAX_LICENCE_DURATION,
    DEFAULT_MAX_LICENCES,
    DEFAULT_MAX_LICENCES_PER_HOLDER,
    Licence,
    Licences,
)
from services.apps.registry.registration import (
    DEFAULT_MAX_REGISTRATIONS,
    DEFAULT_REGISTER_TIMEOUT,
    RESERVED_SERVICE_NAMES,
)
from services.apps.registry.service import (
    SESSION_HOLDER_PREFIX,
    Caller,
    CallerSource,
    LicenceCheck,
    ProviderCheck,
    Registry,
    RegistryService,
    proves_identity,
)
from services.apps.registry.urls import REGISTRABLE_SCHEMES, check_url

__all__ = [
    "AVAILABILITIES",
    "DEFAULT_ALLOW",
    "DEFAULT_LICENCE_DURATION",
    "DEFAULT_MAX_LICENCES",
    "DEFAULT_MAX_LICENCES_PER_HOLDER",
    "DEFAULT_MAX_LICENCE_DURATION",
    "DEFAULT_MAX_REGISTRATIONS",
    "DEFAULT_REGISTER_TIMEOUT",
    "REGISTRABLE_SCHEMES",
    "RESERVED_SERVICE_NAMES",
    "SESSION_HOLDER_PREFIX",
    "STATES",
    "AllowList",
    "Caller",
    "CallerSource",
    "Lease",
    "Licence",
    "LicenceCheck",
    "Licences",
    "ProviderCheck",
    "Registry",
    "RegistryService",
    "ServiceEntry",
    "ServiceList",
    "check_url",
    "parse_allow_entry",
    "proves_identity",
]
