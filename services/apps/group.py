"""The group (swarm) service: many robots behind one Property Service.

A :class:`Group` holds member services found in a
:class:`~services.kernel.directory.Directory` — named statically, or chosen by a
registry query that is asked again whenever a service joins or leaves — and
serves them as one mobile robot:

* ``robots`` lists the members; ``robots.<name>.<property>`` is the member's
  own property (Get, Set and Listen are forwarded, so ``robots.*.location``
  works through the gateway's wildcard expansion).
* ``location`` is the members' centroid, kept current from a Listen on every
  member's ``location``.
* ``behaviors.moveto`` sends every member to the target plus its place in a
  formation (``line``, ``grid``, ``circle``; see :mod:`services.apps.formations`),
  all members at once, each under ``member_timeout``; ``behaviors.stop``
  stops them all (the same name as a robot's).
* ``velocity``: a Get is the mean of the members' velocities; a Set sends
  the velocity command to every member, each clipping it to its own limits
  (a group is teleoperated like one robot).
* ``subgroup`` selects members into a named subgroup under
  ``subgroups.<name>``, itself a Group; ``dissolve`` removes one.

A group call that fails on some members still lets the others act; then it
raises :class:`GroupCallFailed` naming every member that failed and why
(the code is that of the first failure in name order), and ``failed``
lists ``(member CODE)`` pairs of the last group call.

Every call the group makes to a member for a client (a ``robots.<name>.<path>``
Get, Set or Listen, a fan-out of ``velocity`` or ``behaviors.moveto``) goes
through the directory, which checks it against the gateway's rules as that
client, for the member's own name and path: a member the client may not drive
fails the call as any failing member does (PERMISSION_DENIED), and a wildcard
skips what the client may not read. The group's own work (following the
members' locations for its centroid, asking the registry for its members) is
checked as nobody's.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import math
import urllib.parse
from collections.abc import Awaitable, Callable, Iterable, Mapping
from typing import Annotated, Any

import numpy as np

from services.apps.formations import FORMATIONS, centroid, formation_targets, natural_key
from services.apps.location_following import LocationFollower
from services.apps.query import Query
from services.kernel.backend import Backend, Subscription, close_quietly
from services.kernel.core import Prop, Resource, functional, read_write, start_tree, stop_tree
from services.kernel.core.metadata import RESERVED_NAMES
from services.kernel.directory import Directory, own_context, own_work
from services.kernel.errors import (
    AlreadyExists,
    Code,
    DeadlineExceeded,
    InvalidArgument,
    NotFound,
    PropertyError,
    Unavailable,
)
from services.kernel.paths import validate_service_name
from services.kernel.values import (
    Marker,
    Value,
    Vector,
    as_text,
    format_marker,
    format_value,
    parse_names,
    parse_vector,
)
from services.kernel.worker_pool import run_bounded

__all__ = ["DEFAULT_MEMBER_TIMEOUT", "Group", "GroupCallFailed", "query_params"]

log = logging.getLogger(__name__)

DEFAULT_MEMBER_TIMEOUT = 5.0
#: Member calls running at once in one group call; a group of 10,000 does
#: not open 10,000 device requests in the same instant.
MAX_CONCURRENT_CALLS = 1000
#: Failures spelled out in one error message; the rest are counted.
_MAX_LISTED_FAILURES = 10

# The groups whose call is running in this task chain: a group that (through
# its members) reaches itself fails instead of recursing forever.
_ACTIVE: contextvars.ContextVar[frozenset[int]] = contextvars.ContextVar("active_groups", default=frozenset())


class GroupCallFailed(PropertyError):
    """A group call failed on some members; ``failures`` maps each to its error."""

    def __init__(self, what: str, failures: Mapping[str, PropertyError], total: int) -> None:
        names = sorted(failures, key=natural_key)
        listed = "; ".join(
            f"{n}: {failures[n].code.name}: {failures[n].message}" for n in names[:_MAX_LISTED_FAILURES]
        )
        more = len(names) - _MAX_LISTED_FAILURES
        if more > 0:
            listed += f"; and {more} more"
        ok = total - len(names)
        others = f" (the other {ok} acted)" if ok else ""
        super().__init__(
            f"{what} failed on {len(names)} of {total} members{others}: {listed}", failures[names[0]].code
        )
        self.failures = dict(failures)


def query_params(query: Mapping[str, Any] | str) -> dict[str, str]:
    """Query parameters as text, from a config table or a query string.

    ``{type = "mobile_robot", near = [5, 5, 0], radius = 3}`` and
    ``"type=mobile_robot&near=(5 5 0)&radius=3"`` give the same parameters.
    Raises InvalidArgument for a malformed string or an unknown parameter.
    """
    if isinstance(query, str):
        try:
            pairs = urllib.parse.parse_qsl(query.strip(), keep_blank_values=True, strict_parsing=True)
        except ValueError:
            raise InvalidArgument(
                f"expected a query like type=mobile_robot&near=(5 5 0)&radius=3, got {query[:80]!r}"
            ) from None
        params = dict(pairs)
    else:
        params = {}
        for key, value in query.items():
            if isinstance(value, list | tuple):
                params[str(key)] = format_value(np.asarray(value, dtype=np.float64))
            else:
                params[str(key)] = format_value(value)
    Query.parse(params)
    return params


class Members(Resource):
    """The group's members: one namespace per member, holding all of its properties."""


class Parts(Resource):
    """A namespace of the mobile-robot property set that a group fills per member (``robots.*``)."""


class Subgroups(Resource):
    """Named subgroups of this group, each a group itself."""


class GroupBehaviors(Resource):
    """What the whole group can be asked to do."""

    def __init__(self, group: Group) -> None:
        self._group = group

    @functional(doc="drive every member to the target plus its place in a formation")
    async def moveto(self, target: Marker, *, formation: str = "line", spacing: float = 1.0) -> list[str]:
        """Send every member to its formation place around the target; returns the members that accepted."""
        return await self._group.moveto(target, formation=formation, spacing=spacing)

    # Also the name of the Resource lifecycle hook: being functional, it is the
    # property only, so a gateway shutting down never stops the group's robots;
    # it answers like every group call (the members that acted), hence the override.
    @functional(doc="stop every member where it is (each member's behaviors.stop)")
    async def stop(self) -> list[str]:  # type: ignore[override]
        """Stop every member; returns the members that stopped."""

        def stop(name: str, backend: Backend) -> Awaitable[Value]:
            return backend.set("behaviors.stop", "")

        return await self._group.fan_out("behaviors.stop", stop)


class Group(Resource):
    """A group of robots served as one mobile robot (see the module documentation)."""

    resource_type = "group"

    robots: Members
    behaviors: GroupBehaviors
    actuators: Parts
    sensors: Parts
    subgroups: Subgroups
    failed: Annotated[
        list[Any], Prop(readonly=True, doc="(member CODE) pairs of members that failed the last group call")
    ]
    query: Annotated[
        str, Prop(readonly=True, doc="the registry query choosing the members, empty when static")
    ]
    member_timeout: Annotated[float, Prop(doc="seconds each member gets to answer a group call")]

    def __init__(
        self,
        *,
        directory: Directory,
        members: Iterable[str] | None = None,
        query: Mapping[str, Any] | str | None = None,
        registry: str = "registry",
        member_timeout: float = DEFAULT_MEMBER_TIMEOUT,
        within: Group | None = None,
    ) -> None:
        if members is not None and query is not None:
            raise InvalidArgument("a group takes members or a query, not both")
        if not (math.isfinite(member_timeout) and member_timeout > 0):
            raise InvalidArgument(
                f"member_timeout must be a positive number of seconds, not {member_timeout}"
            )
        self._directory = directory
        self._registry = registry
        self._within = within
        self._static: list[str] | None = None
        self._query: dict[str, str] | None = None
        if query is not None:
            self._query = query_params(query)
        else:
            self._static = _member_names(members if members is not None else [])
        self.robots = Members()
        self.behaviors = GroupBehaviors(self)
        self.actuators = Parts()
        self.sensors = Parts()
        self.subgroups = Subgroups()
        self.failed = []
        self.query = (
            urllib.parse.urlencode(self._query, safe="() ", quote_via=urllib.parse.quote)
            if self._query
            else ""
        )
        self.member_timeout = float(member_timeout)
        self._wanted: set[str] = set(self._static or ())
        self._locations: dict[str, Vector] = {}
        self._following = LocationFollower(
            self._store_location, timeout=lambda: self.member_timeout, what="group"
        )
        self._location_pending = False
        self._unwatch: Callable[[], None] | None = None
        self._refresh_task: asyncio.Task[None] | None = None
        self._refresh_again = False
        self._started = False
        self._registry_sub: Subscription | None = None
        self._registry_backend: Backend | None = None

    # -- lifecycle -------------------------------------------------------

    async def start(self) -> None:
        self._started = True
        self._unwatch = self._directory.watch(self._on_directory)
        if self._query is not None:
            await self.refresh()
        else:
            self._sync()
        # The members found at start report their locations before the group counts as started.
        await self._following.settled(self.member_timeout)

    async def stop(self) -> None:
        self._started = False
        if self._unwatch is not None:
            self._unwatch()
            self._unwatch = None
        if self._refresh_task is not None:
            self._refresh_task.cancel()
            await asyncio.gather(self._refresh_task, return_exceptions=True)
        await self._following.aclose()
        if self._registry_sub is not None:
            await close_quietly(self._registry_sub)
            self._registry_sub = None

    # -- members ---------------------------------------------------------

    def member_names(self) -> list[str]:
        """The members right now, in natural name order."""
        return sorted(self.robots.children(), key=natural_key)

    async def refresh(self) -> None:
        """Ask the registry for the query's members now and update ``robots``."""
        if self._query is None:
            self._sync()
            return
        try:
            # Who the members are is the group's own business, whoever's call made it ask.
            with own_work():
                registry = self._directory.backend(self._registry)
                await self._follow_registry(registry)
                async with asyncio.timeout(self.member_timeout):
                    text = await registry.get("find", self._query)
        except TimeoutError:
            log.warning("group query: the registry %r did not answer in time", self._registry)
            return
        except PropertyError as e:
            # A group being stopped (the gateway shutting down) may find the registry gone: expected.
            level = logging.WARNING if self._started else logging.DEBUG
            log.log(level, "group query: the registry %r refused it: %s", self._registry, e.message)
            return
        self._wanted = set(parse_names(as_text(text, "find")))
        self._sync()

    async def _follow_registry(self, registry: Backend) -> None:
        """Ask again whenever the registry's table changes (a type learned, a state changed)."""
        if self._registry_sub is not None and self._registry_backend is registry:
            return
        if self._registry_sub is not None:
            await close_quietly(self._registry_sub)
            self._registry_sub = None
        try:
            async with asyncio.timeout(self.member_timeout):
                sub = await registry.listen("revision", lambda change: self._schedule_refresh())
        except (PropertyError, TimeoutError):
            return  # a registry without a revision: joins and leaves still trigger a refresh
        self._registry_sub = sub
        self._registry_backend = registry

    def _candidates(self) -> set[str]:
        wanted = set(self._wanted)
        if self._within is not None:
            wanted &= set(self._within.robots.children())
        return wanted

    def _sync(self) -> None:
        if not self._started:
            return
        present = set(self.robots.children())
        wanted = self._candidates()
        for name in sorted(present - wanted, key=natural_key):
            self._drop(name)
        known = set(self._directory.names())
        for name in sorted(wanted - present, key=natural_key):
            if name in known:
                self._add(name)
        self._sync_subgroups()

    def _add(self, name: str) -> None:
        try:
            backend = self._directory.backend(name)
        except PropertyError:
            return
        if backend.serves(self):
            log.warning("group: skipping %r, which is this group itself", name)
            return
        if self._query is not None and backend.info.type == "group" and "type" not in self._query:
            return  # a query group never swallows other groups (or itself) unless asked for groups
        if name in RESERVED_NAMES:
            log.warning("group: a member cannot be named %r", name)
            return
        self.robots.attach(name, backend)
        self._following.follow(name, backend)

    def _drop(self, name: str) -> None:
        self.robots.detach(name)
        self._following.forget(name)
        if self._locations.pop(name, None) is not None:
            self._location_changed()

    def _on_directory(self, name: str, backend: Backend | None) -> None:
        if not self._started:
            return
        if self._query is not None:
            self._schedule_refresh()
        elif backend is None and name in self.robots.children():
            self._drop(name)
            self._sync_subgroups()
        elif backend is not None and name in self._wanted:
            self._sync()

    def _sync_subgroups(self) -> None:
        for sub in self.subgroups.children().values():
            if isinstance(sub, Group):
                sub._sync()

    def _schedule_refresh(self) -> None:
        if not self._started:
            return
        if self._refresh_task is not None and not self._refresh_task.done():
            self._refresh_again = True
            return
        self._refresh_task = asyncio.get_running_loop().create_task(
            self._refresh_loop(), name="group: refresh", context=own_context()
        )

    async def _refresh_loop(self) -> None:
        self._refresh_again = True
        while self._refresh_again:
            self._refresh_again = False
            await asyncio.sleep(0)  # let a burst of joins and leaves arrive first
            await self.refresh()

    # -- location ----------------------------------------------------------

    def _store_location(self, name: str, vector: Vector | None) -> None:
        # A member without a location (or unreachable now) does not count in the centroid.
        if vector is None:
            if self._locations.pop(name, None) is None:
                return
        else:
            self._locations[name] = vector
        self._location_changed()

    def _location_changed(self) -> None:
        # Many members move in the same instant; listeners get one centroid per loop turn.
        if self._location_pending:
            return
        self._location_pending = True
        asyncio.get_running_loop().call_soon(self._announce_location)

    def _announce_location(self) -> None:
        self._location_pending = False
        self.changed("location")

    @property
    def location(
        self,
    ) -> Annotated[Vector, Prop(readonly=True, gui="pose", doc="centroid of the members' locations")]:
        """The members' centroid (positions averaged, headings by circular mean)."""
        if not self._locations:
            raise Unavailable("no member of this group reports a location")
        return centroid(list(self._locations.values()))

    # -- group calls -------------------------------------------------------

    async def fan_out(
        self,
        what: str,
        call: Callable[[str, Backend], Awaitable[Any]],
        names: Iterable[str] | None = None,
    ) -> list[str]:
        """Run ``call(name, backend)`` for every member at once, each under ``member_timeout``.

        Returns the members that succeeded, in name order; when any failed,
        raises :class:`GroupCallFailed` after all have finished, and
        ``failed`` lists them.
        """
        active = _ACTIVE.get()
        if id(self) in active:
            raise PropertyError(f"{what}: the group is among its own members", Code.FAILED_PRECONDITION)
        _ACTIVE.set(active | {id(self)})
        try:
            return await self._fan_out(what, call, names)
        finally:
            # Set back rather than reset by token: a call started inline and finished in a task
            # (a Session's) ends in another context than it began, where a token is refused.
            _ACTIVE.set(active)

    async def _fan_out(
        self, what: str, call: Callable[[str, Backend], Awaitable[Any]], names: Iterable[str] | None
    ) -> list[str]:
        members = self.robots.children()
        chosen = self.member_names() if names is None else list(names)
        failures: dict[str, PropertyError] = {}
        for name in self._missing():
            failures[name] = Unavailable("not registered right now")
        timeout = self.member_timeout

        async def one(name: str) -> None:
            backend = members.get(name)
            if not isinstance(backend, Backend):
                failures[name] = NotFound("not a member any more")
                return
            try:
                async with asyncio.timeout(timeout):
                    await call(name, backend)
            except TimeoutError:
                failures[name] = DeadlineExceeded(f"no answer within {timeout:g} s")
            except PropertyError as e:
                failures[name] = e
            except Exception as e:  # one broken member must not break the group call
                log.exception("group call %s on member %s failed", what, name)
                failures[name] = PropertyError(f"internal error: {type(e).__name__}", Code.INTERNAL)

        await run_bounded(chosen, one, MAX_CONCURRENT_CALLS)
        ordered = sorted(failures, key=natural_key)
        self.failed = [[name, failures[name].code.name] for name in ordered]
        if failures:
            raise GroupCallFailed(what, failures, len(set(chosen) | set(failures)))
        return [n for n in chosen if n not in failures]

    def _missing(self) -> list[str]:
        """Static members that are not registered now (a query group has none by definition)."""
        if self._static is None:
            return []
        present = self.robots.children()
        candidates = self._candidates()
        return [n for n in self._static if n in candidates and n not in present]

    async def moveto(self, target: Marker, *, formation: str = "line", spacing: float = 1.0) -> list[str]:
        """Send each member to ``target`` plus its formation offset; see :class:`GroupBehaviors`."""
        location = target.location
        if location is None:
            raise InvalidArgument(
                "the target marker has no location: send <marker><location>(x y)</location></marker>"
            )
        if formation not in FORMATIONS:
            raise InvalidArgument(f"unknown formation {formation!r}: use one of {', '.join(FORMATIONS)}")
        names = self.member_names()
        places = formation_targets(names + self._missing(), location, formation, spacing)
        markers = {name: format_marker(target.with_field("location", places[name])) for name in names}

        def send(name: str, backend: Backend) -> Awaitable[Value]:
            return backend.set("behaviors.moveto", markers[name])

        return await self.fan_out("behaviors.moveto", send, names)

    # One name, read and written: the value is positional-only so that a Get can
    # never carry a command (reads do not move robots).
    @read_write(
        unit="m/s, rad/s",
        doc="Get: the mean velocity of the members that answer; "
        "Set: the velocity command for every member, each clipping it to its own limits",
    )
    async def velocity(self, command: Vector | None = None, /) -> Vector | list[str]:
        """Get: the members' mean velocity; Set: command every member, return those that took it."""
        if command is None:
            return await self.mean_velocity()
        return await self.command_velocity(command)

    async def mean_velocity(self) -> Vector:
        """The mean of the members' velocities (asked now, each under ``member_timeout``)."""
        found: dict[str, Vector] = {}

        async def ask(name: str, backend: Backend) -> None:
            found[name] = parse_vector(as_text(await backend.get("velocity"), "velocity"))

        try:
            await self.fan_out("velocity", ask)
        except GroupCallFailed:
            if not found:
                raise
        if not found:
            raise Unavailable("the group has no members")
        return centroid(list(found.values()))

    async def command_velocity(self, command: Vector) -> list[str]:
        """Set ``velocity`` of every member to ``command``; returns the members that took it.

        Each member clips the command to its own limits and stops by itself
        when it is not renewed; a member that refuses it fails the call like
        any group call (the others still drive).
        """
        if command.ndim != 1 or command.size == 0:
            raise InvalidArgument("a velocity command is a vector like (vx vy [vz [wx wy wz]])")
        text = format_value(command)

        def send(name: str, backend: Backend) -> Awaitable[Value]:
            return backend.set("velocity", text)

        return await self.fan_out("velocity", send)

    # -- subgroups -------------------------------------------------------

    @functional(doc="select members into a named subgroup, by names or by a registry query")
    async def subgroup(self, name: str, *, members: list[str] | None = None, query: str = "") -> list[str]:
        """Create ``subgroups.<name>`` from ``members`` (names of this group's members) or a ``query``.

        The query is in query-string form (``type=mobile_robot&near=(5 5 0)&radius=3``)
        and is kept current like this group's; a subgroup only ever holds
        members of this group. Returns the subgroup's members.
        """
        validate_service_name(name)
        if name in self.subgroups.children():
            raise AlreadyExists(f"subgroup {name!r} already exists; dissolve it first")
        if members is None and not query:
            raise InvalidArgument(
                "a subgroup needs members (a list of names) or a query "
                "(e.g. type=mobile_robot&near=(4 5)&radius=2): give one of the two parameters"
            )
        if members is not None and query:
            raise InvalidArgument("give a subgroup either members (a list of names) or a query, not both")
        if members is not None:
            current = set(self.robots.children())
            strangers = [m for m in members if m not in current]
            if strangers:
                raise InvalidArgument(f"not members of this group: {' '.join(strangers)}")
        sub = Group(
            directory=self._directory,
            members=members,
            query=query or None,
            registry=self._registry,
            member_timeout=self.member_timeout,
            within=self,
        )
        self.subgroups.attach(name, sub)
        if self._started:
            await start_tree(sub)  # idempotent: the core starts it too, a moment later
        return sub.member_names()

    @functional(doc="remove a subgroup (its members stay in this group)")
    async def dissolve(self, name: str) -> None:
        """Remove ``subgroups.<name>``."""
        sub = self.subgroups.children().get(name)
        if sub is None:
            raise NotFound(f"no subgroup named {name!r}")
        self.subgroups.detach(name)
        if isinstance(sub, Group):
            await stop_tree(sub)  # idempotent, as above


def _member_names(members: Iterable[str]) -> list[str]:
    if isinstance(members, str):
        raise InvalidArgument("members must be a list of names, not one string")
    names: dict[str, None] = {}
    for name in members:
        validate_service_name(name)
        if name in RESERVED_NAMES:
            raise InvalidArgument(f"a member cannot be named {name!r}")
        names[name] = None
    return list(names)
