"""The kinds of in-process services a gateway configuration (or a device CLI) can create by name.

``[[services]] name = "scout1", type = "sim-robot", options = {start = [1, 2]}``
becomes ``create("sim-robot", start=[1, 2])``.

A kind whose factory takes a ``directory`` (a group of robots reaches its
members through the gateway's directory) gets the one passed to
:func:`create`; the others never see it, so a device process, which has no
directory, can still create every kind that does not need one. A kind whose factory takes a
``follow`` (the recorder: :data:`services.kernel.follow.Follow`, a Listen of its own) gets the
gateway's when one is passed to :func:`build`; no configuration gives it.

A kind may also name your own class by import path, ``package.module:Class``
(a :class:`~services.kernel.core.Resource` subclass, or a function returning one):
``type = "lamps:Lamp"`` serves ``Lamp`` from ``lamps.py`` on the Python path.
"""

from __future__ import annotations

import importlib
import inspect
import re
import typing
from collections.abc import Callable, Mapping
from typing import Any

from services.apps.environment import EnvironmentModel
from services.apps.group import Group
from services.apps.recorder import Recorder
from services.apps.replay import Replay
from services.apps.simulators import SimRobot, SimSensor
from services.apps.statemachine import StateMachineService
from services.apps.storage import Storage
from services.apps.vision import Camera
from services.kernel.core import Resource
from services.kernel.directory import Directory
from services.kernel.errors import InvalidArgument
from services.kernel.follow import Follow

__all__ = [
    "CATALOG",
    "PATH_OPTIONS",
    "PATH_TABLE_OPTIONS",
    "build",
    "create",
    "factory_of",
    "needs_directory",
    "takes_follow",
]

CATALOG: dict[str, Callable[..., Resource]] = {
    "camera": Camera,
    "environment": EnvironmentModel,
    "group": Group,
    "recorder": Recorder,
    "replay": Replay,
    "sim-robot": SimRobot,
    "sim-sensor": SimSensor,
    "statemachine": StateMachineService,
    "storage": Storage,
}

#: Options of a kind that name a file or folder: a configuration takes a relative one from its
#: own folder (``gateway.config``), as it does for every other path it holds.
PATH_OPTIONS: dict[str, tuple[str, ...]] = {
    "recorder": ("folder",),
    "replay": ("recording",),
    "storage": ("directory",),
}
#: Options of a kind that are tables of name → file, taken from the config's folder alike; a value
#: with the given prefix names something else (``builtin:patrol``, a chart shipped with the package).
PATH_TABLE_OPTIONS: dict[str, tuple[tuple[str, str], ...]] = {"statemachine": (("charts", "builtin:"),)}

#: The keyword a factory declares to be handed the gateway's directory.
_DIRECTORY = "directory"
#: The keyword a factory declares to be handed the gateway's :data:`Follow`.
_FOLLOW = "follow"
#: Keywords of a factory that are for the service's own use, never options from a config.
_INTERNAL: dict[str, tuple[str, ...]] = {"environment": ("clock",), "group": ("within",)}


def _parameters(factory: Callable[..., Resource]) -> dict[str, inspect.Parameter]:
    try:
        return dict(inspect.signature(factory).parameters)
    except (TypeError, ValueError):
        return {}


def _imported(kind: str) -> Callable[..., Resource]:
    """The factory named by an import path ``package.module:Name``."""
    module_name, _, attr = kind.partition(":")
    if not module_name or not attr:
        raise InvalidArgument(f"bad service type {kind!r}: an import path looks like 'package.module:Class'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as e:
        hint = ""
        if isinstance(e, ModuleNotFoundError) and e.name == module_name.partition(".")[0]:
            # The usual slip with a module of one's own: it sits in the current folder, which the
            # installed `psgateway` script (unlike `python -m`) does not import from.
            hint = " (imported from the installed packages and PYTHONPATH: PYTHONPATH=. for one here)"
        raise InvalidArgument(f"service type {kind!r}: cannot import {module_name!r}: {e}{hint}") from None
    factory: Any = module
    for part in attr.split("."):
        factory = getattr(factory, part, None)
        if factory is None:
            raise InvalidArgument(f"service type {kind!r}: {module_name!r} has no {attr!r}")
    if isinstance(factory, type) and not issubclass(factory, Resource):
        raise InvalidArgument(
            f"service type {kind!r}: {attr} is not a services.kernel.core.Resource subclass"
        )
    if not callable(factory):
        raise InvalidArgument(f"service type {kind!r}: {attr} is not a class or function")
    return factory  # type: ignore[no-any-return]


def factory_of(kind: str) -> Callable[..., Resource]:
    """The factory for ``kind``: a catalog name or an import path; InvalidArgument if there is none."""
    factory = CATALOG.get(kind)
    if factory is not None:
        return factory
    if ":" in kind:
        return _imported(kind)
    raise InvalidArgument(
        f"unknown service type {kind!r}: known types are {', '.join(sorted(CATALOG))}, "
        "or an import path 'package.module:Class'"
    )


def _takes_directory(param: inspect.Parameter) -> bool:
    """A ``directory`` keyword typed as the gateway's :class:`Directory` (a storage service's
    ``directory`` option, a folder's path, is no such keyword)."""
    annotation = param.annotation
    if isinstance(annotation, str):
        return re.search(r"\bDirectory\b", annotation) is not None
    return annotation is Directory or Directory in typing.get_args(annotation)


def needs_directory(kind: str) -> bool:
    """True when services of ``kind`` reach other services (a group) and so need the gateway's directory."""
    try:
        factory = factory_of(kind)
    except InvalidArgument:
        return False
    param = _parameters(factory).get(_DIRECTORY)
    return param is not None and _takes_directory(param)


def takes_follow(kind: str) -> bool:
    """True when services of ``kind`` follow changes as a Listen does (the recorder), and so are
    handed the gateway's :data:`Follow`."""
    try:
        factory = factory_of(kind)
    except InvalidArgument:
        return False
    return _FOLLOW in _parameters(factory) and kind in CATALOG


def _internal(kind: str) -> tuple[str, ...]:
    """Keywords of ``kind``'s factory that no config may give."""
    internal = (_DIRECTORY, *_INTERNAL.get(kind, ())) if needs_directory(kind) else _INTERNAL.get(kind, ())
    return (*internal, _FOLLOW) if takes_follow(kind) else internal


def _accepted(kind: str, factory: Callable[..., Resource]) -> str:
    internal = _internal(kind)
    params = _parameters(factory)
    if not params:
        return "see its documentation"
    names = [
        p.name
        for p in params.values()
        if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and p.name not in internal
    ]
    return ", ".join(names) or "none"


def create(kind: str, *, directory: Directory | None = None, **options: Any) -> Resource:
    """Create a service object of ``kind``; InvalidArgument for an unknown kind or bad options.

    ``directory`` is handed on only to kinds that take one (see :func:`needs_directory`);
    such a kind created without one is an InvalidArgument. Options from a config go
    through :func:`build`, where an option may be named ``directory`` too (a storage
    service's folder).
    """
    return build(kind, options, directory)


def build(
    kind: str, options: Mapping[str, Any], directory: Directory | None = None, follow: Follow | None = None
) -> Resource:
    """:func:`create` with the options as a mapping: any option name, ``directory`` included;
    ``follow`` is handed to the kinds that take one (:func:`takes_follow`)."""
    factory = factory_of(kind)
    for key in _internal(kind):
        if key in options:
            raise InvalidArgument(
                f"bad options for {kind!r}: {key!r} is not an option; it accepts: {_accepted(kind, factory)}"
            )
    options = dict(options)
    if needs_directory(kind):
        if directory is None:
            raise InvalidArgument(f"a {kind!r} service reaches other services: it runs only inside a gateway")
        options[_DIRECTORY] = directory
    if follow is not None and takes_follow(kind):
        options[_FOLLOW] = follow
    try:
        signature: inspect.Signature | None = inspect.signature(factory)
    except ValueError:
        signature = None
    if signature is not None:
        # Said in the project's own words: Python's TypeError texts differ between versions.
        missing = [
            p.name
            for p in signature.parameters.values()
            if p.default is p.empty
            and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
            and p.name not in options
        ]
        if missing:
            raise InvalidArgument(
                f"bad options for {kind!r}: missing a required argument: {missing[0]!r}; "
                f"it accepts: {_accepted(kind, factory)}"
            )
    try:
        bound = signature.bind(**options) if signature is not None else None
    except TypeError as e:
        accepted = _accepted(kind, factory)
        raise InvalidArgument(f"bad options for {kind!r}: {e}; it accepts: {accepted}") from None
    try:
        made = factory(**options) if bound is None else factory(*bound.args, **bound.kwargs)
    except InvalidArgument as e:
        raise InvalidArgument(f"bad options for {kind!r}: {e.message}") from None
    except (TypeError, ValueError) as e:
        raise InvalidArgument(f"bad options for {kind!r}: {e}") from None
    if not isinstance(made, Resource):
        raise InvalidArgument(
            f"service type {kind!r} made a {type(made).__name__}, not a services.kernel.core.Resource"
        )
    return made
