"""The storage service: a directory whose files are properties (see ``docs/storage.md``).

:class:`Storage` is the Resource: ``files`` (the live list), ``info``,
``find``, ``remove`` and the read-only settings, served by the class wrapper.
``file`` (a file as text) and ``blob`` (a file as bytes, a binary value) are
read, written and followed with the parameter ``name``, which the class wrapper
cannot express for a Set or a Listen: :class:`StorageService`, the LocalService
subclass that serves a Storage (``Storage.served_by``), takes those two calls
on ``file`` and ``blob`` and declares both in the model.

Disk work runs on the service's own worker threads (:data:`WORKERS`), never
on the event loop; changes made by others on disk arrive through
:class:`~services.apps.storage.watcher.DirectoryWatcher`.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import itertools
import logging
import mimetypes
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Annotated, Any, TypeVar

from services.apps.storage.disk import FileInfo, Folder
from services.apps.storage.find import FindQuery, format_time, glob_matcher
from services.apps.storage.names import check_name
from services.apps.storage.watcher import DirectoryWatcher
from services.kernel.backend import NO_PARAMS, Change, Notify, OnRaise, Subscription, tell_each
from services.kernel.core import LocalService, Prop, Resource, action, query
from services.kernel.errors import (
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    PropertyError,
    ReadOnly,
    ResourceExhausted,
    Unavailable,
)
from services.kernel.model import Access, ParameterModel, PropertyModel
from services.kernel.values import Marker, Value

__all__ = ["MAX_FILE_SIZE", "MAX_LISTED", "Storage", "StorageService"]

log = logging.getLogger(__name__)

T = TypeVar("T")

#: The largest file a Get can carry: gRPC's default message limit (4 MiB, ``gateway.engine.sizes``),
#: less 64 KiB for what travels with the value (service, property, parameters, a Session's
#: envelope). A unit test holds it under the gateway's answer limit.
MAX_FILE_SIZE = 4 * 1024 * 1024 - 64 * 1024
#: Names in ``files`` and in one ``find`` answer; a bigger directory is narrowed with ``find``.
MAX_LISTED = 10_000
#: Worker threads for disk calls of one service: fsyncs of different files overlap, a slow
#: disk cannot take every thread of the process.
WORKERS = 4
#: Disk calls waiting for a worker at once; beyond, a call is RESOURCE_EXHAUSTED.
MAX_WAITING_CALLS = 1024
#: Files followed by Listens at once (each listen of the same file shares one).
MAX_FOLLOWED = 1024


class _Unreadable:
    """A followed file that exists but cannot be carried (not text for ``file``, too big, a link)."""

    def __repr__(self) -> str:
        return "unreadable"


_UNREADABLE = _Unreadable()
#: What a follower knows of its file: the text (``file``) or the bytes (``blob``), None (no such
#: file) or _UNREADABLE.
_State = Value | None | _Unreadable
#: The two properties a file is read, written and followed through.
FILE = "file"
BLOB = "blob"


class _Followed:
    """The listens of one file through one property (``file`` or ``blob``), and what they last heard."""

    __slots__ = ("again", "last", "listeners", "name", "prop", "reading")

    def __init__(self, name: str, prop: str) -> None:
        self.name = name
        self.prop = prop
        self.listeners: dict[int, Notify] = {}
        self.last: _State = _UNREADABLE
        self.reading = False
        self.again = False


class _FileSubscription(Subscription):
    __slots__ = ("_entry", "_storage", "_token")

    def __init__(self, storage: Storage, entry: _Followed, token: int) -> None:
        self._storage = storage
        self._entry = entry
        self._token = token

    async def close(self) -> None:
        self._storage._unfollow(self._entry, self._token)


def media_type(name: str) -> str:
    """The media type of ``name`` by its extension (Python's mimetypes); octet-stream when unknown."""
    guessed, _ = mimetypes.guess_type(name, strict=False)
    return guessed or "application/octet-stream"


def _setting(value: Any, kind: type, what: str) -> Any:
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        names = {str: "text", int: "a whole number", bool: "true or false"}
        raise InvalidArgument(f"{what} must be {names[kind]}, got {value!r}")
    return value


class StorageService(LocalService):
    """Serves a :class:`Storage`: the class wrapper's calls, plus Set and Listen of ``file`` by ``name``."""

    def __init__(self, obj: Resource, url: str = "local") -> None:
        if not isinstance(obj, Storage):
            raise TypeError(f"StorageService serves a Storage, not a {type(obj).__name__}")
        super().__init__(obj, url)
        self.storage = obj

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        if path in ("file.parameters", "blob.parameters"):
            return FILE_PARAMETERS  # `name` is required, which a query's parameters cannot say
        if path == "blob.media_type":
            # The media type of the file `name` names (by its extension); "" without one.
            return media_type(_file_name(params, "blob.media_type")) if params else ""
        return await super().get(path, params)

    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        if path == FILE:
            if isinstance(value, bytes):
                raise InvalidArgument(
                    "`file` holds text: send its value as text, or Set `blob` (same `name`) to store bytes"
                )
            return await self.storage.store(_file_name(params, path), value)
        if path == BLOB:
            if isinstance(value, str):
                raise InvalidArgument(
                    "`blob` is binary (type bytes): send its value as bytes (the `data` field;"
                    " `\\=BASE64` on a line; `psctl set --file`), "
                    "or Set `file` (same `name`) to store text"
                )
            return await self.storage.store_bytes(_file_name(params, path), value)
        return await super().set(path, value, params)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        if path in (FILE, BLOB):
            return await self.storage.follow(_file_name(params, path), notify, path)
        return await super().listen(path, notify, params)

    def model_of(self, prop: PropertyModel) -> PropertyModel:
        if prop.name == FILE:
            return FILE_MODEL
        if prop.name == BLOB:
            return dataclasses.replace(BLOB_MODEL, max_size=self.storage.max_file_size)
        return prop


def _file_name(params: Mapping[str, str], prop: str = FILE) -> str:
    extra = sorted(k for k in params if k != "name")
    if extra:
        raise InvalidArgument(f"`{prop}` has no parameter `{extra[0]}`; it accepts: `name`")
    name = params.get("name")
    if name is None:
        raise InvalidArgument(f"`{prop}` needs the parameter `name` (the file's relative path)")
    return check_name(name)


#: ``file.parameters`` and ``blob.parameters``: one required parameter.
FILE_PARAMETERS = "((name text -))"
FILE_MODEL = PropertyModel(
    name="file",
    type="text",
    access=Access.READ_WRITE,
    doc='the content of file `name` (UTF-8 text); a Set stores it atomically, a Set of "" removes it',
    gui="text",
    value=ParameterModel("value", "text", required=False, doc='the new content; "" removes the file'),
    parameters=(
        ParameterModel("name", "text", required=True, doc="the file's relative path, / between directories"),
    ),
)
BLOB_MODEL = PropertyModel(
    name="blob",
    type="bytes",
    access=Access.READ_WRITE,
    doc="the content of file `name` as bytes (any file: an image, an array); a Set stores it atomically; "
    "the media type follows the name's extension (`blob.media_type` with `name`)",
    gui="bytes",
    value=ParameterModel("value", "bytes", required=True, doc="the new content, bytes"),
    parameters=(
        ParameterModel("name", "text", required=True, doc="the file's relative path, / between directories"),
    ),
)


class Storage(Resource):
    """A directory whose files are properties: read, stored, removed, found and followed by name."""

    resource_type = "storage"
    served_by = StorageService

    files: Annotated[list[str], Prop(readonly=True, doc="the files, relative paths with /; Listen to follow")]
    directory: Annotated[str, Prop(readonly=True, doc="the directory whose files are served")]
    max_file_size: Annotated[int, Prop(readonly=True, unit="B", doc="the largest file stored or read")]
    pattern: Annotated[str, Prop(readonly=True, doc='the glob of the files shown ("": all)')]
    read_only: Annotated[bool, Prop(readonly=True, doc="files are read only; Sets are refused")]

    def __init__(
        self,
        *,
        directory: str,
        max_file_size: int = MAX_FILE_SIZE,
        pattern: str = "",
        read_only: bool = False,
    ) -> None:
        """``directory`` is created at start when missing; ``pattern`` selects the files shown."""
        _setting(directory, str, "directory")
        if not directory:
            raise InvalidArgument("directory must name the folder whose files are served")
        _setting(max_file_size, int, "max_file_size")
        if not 1 <= max_file_size <= MAX_FILE_SIZE:
            raise InvalidArgument(
                f"max_file_size must be from 1 to {MAX_FILE_SIZE} bytes (what one message carries), "
                f"got {max_file_size}"
            )
        _setting(pattern, str, "pattern")
        _setting(read_only, bool, "read_only")
        root = Path(directory).expanduser().absolute()
        if root.exists() and not root.is_dir():
            raise InvalidArgument(f"directory {str(root)!r} exists and is not a directory")
        self._root = root
        self._folder = Folder(root)
        self._shown: Callable[[str], bool] = glob_matcher(pattern) if pattern else _everything
        self.files = []
        self.directory = str(root)
        self.max_file_size = max_file_size
        self.pattern = pattern
        self.read_only = read_only
        self._pool: ThreadPoolExecutor | None = None
        self._waiting = 0
        self._watcher: DirectoryWatcher | None = None
        self._followed: dict[tuple[str, str], _Followed] = {}
        self._tokens = itertools.count()
        self._refreshing = False
        self._refresh_again = False
        self._warned_truncated = False

    # -- lifecycle -----------------------------------------------------------------

    async def start(self) -> None:
        try:
            self._root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise FailedPrecondition(
                f"cannot create directory {str(self._root)!r}: {exc.strerror or exc}"
            ) from None
        # Changes are reported against the real path: a directory reached through a link is watched there.
        self._root = self._root.resolve()
        self._folder = Folder(self._root)
        self._pool = ThreadPoolExecutor(WORKERS, thread_name_prefix="storage")
        self._watcher = DirectoryWatcher(self._root, self._on_disk)
        self._watcher.start()
        await self._refresh()

    async def stop(self) -> None:
        if self._watcher is not None:
            await self._watcher.aclose()
            self._watcher = None
        self._followed.clear()
        if self._pool is not None:
            # Running writes finish (each is atomic either way); waiting ones are dropped.
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    async def _disk(self, call: Callable[..., T], *args: Any) -> T:
        """Run a blocking :class:`Folder` call on a worker thread."""
        pool = self._pool
        if pool is None:
            raise FailedPrecondition("the storage service is not running")
        if self._waiting >= MAX_WAITING_CALLS:
            raise ResourceExhausted(
                f"storage: {self._waiting} disk calls are waiting already; try again later"
            )
        self._waiting += 1
        try:
            return await asyncio.get_running_loop().run_in_executor(pool, functools.partial(call, *args))
        finally:
            self._waiting -= 1

    # -- names ---------------------------------------------------------------------

    def _readable(self, name: str) -> str:
        check_name(name)
        if not self._shown(name):
            raise NotFound(f"no file `{name}`: this service shows only files matching {self.pattern!r}")
        return name

    def _writable(self, name: str) -> str:
        if self.read_only:
            raise ReadOnly(f"cannot change `{name}`: this storage service is read-only")
        check_name(name)
        if not self._shown(name):
            raise InvalidArgument(
                f"cannot store `{name}`: this service holds only files matching {self.pattern!r}"
            )
        return name

    # -- the properties ------------------------------------------------------------

    @query(doc="the content of file `name` (UTF-8 text)")
    async def file(self, *, name: str = "") -> str:
        """The content of file ``name`` as text."""
        if not name:
            raise InvalidArgument("`file` needs the parameter `name` (the file's relative path)")
        data = await self._disk(self._folder.read, self._readable(name), self.max_file_size)
        return _text(name, data)

    @query(doc="the content of file `name` as bytes (any file); Set it to store bytes")
    async def blob(self, *, name: str = "") -> bytes:
        """The content of file ``name`` as bytes, whatever it holds."""
        if not name:
            raise InvalidArgument("`blob` needs the parameter `name` (the file's relative path)")
        return await self._disk(self._folder.read, self._readable(name), self.max_file_size)

    async def store(self, name: str, value: str) -> str:
        """Store ``value`` as file ``name`` (what a Set of ``file`` does); "" removes it."""
        self._writable(name)
        if value == "":
            await self.remove(name=name)
            return ""
        limit = self.max_file_size
        if len(value) > limit:  # a character is at least one byte
            raise _too_big(name, len(value), limit)
        try:
            data = value.encode("utf-8")
        except UnicodeEncodeError as exc:
            raise InvalidArgument(
                f"cannot store `{name}`: the value is not valid text ({exc.reason})"
            ) from None
        if len(data) > limit:
            raise _too_big(name, len(data), limit)
        await self._disk(self._folder.write, name, data)
        self._stored(name, data)
        return ""

    async def store_bytes(self, name: str, data: bytes) -> str:
        """Store ``data`` as file ``name`` (what a Set of ``blob`` does; empty bytes make an empty file)."""
        self._writable(name)
        if len(data) > self.max_file_size:
            raise _too_big(name, len(data), self.max_file_size)
        await self._disk(self._folder.write, name, data)
        self._stored(name, data)
        return ""

    @action(doc='remove file `name` (a Set of `file` to "" does the same)')
    async def remove(self, *, name: str) -> None:
        """Remove file ``name``; NotFound when there is none."""
        await self._disk(self._folder.remove, self._writable(name))
        self._stored(name, None)

    @query(doc="size, modification time and media type of file `name`")
    async def info(self, *, name: str = "") -> Marker:
        """``<marker><name/><size/><mtime/><type/></marker>`` of file ``name`` (works on any file)."""
        if not name:
            raise InvalidArgument("`info` needs the parameter `name` (the file's relative path)")
        found: FileInfo = await self._disk(self._folder.info, self._readable(name))
        return Marker(
            "marker",
            {
                "name": name,
                "size": str(found.size),
                "mtime": format_time(found.mtime_ns),
                "type": media_type(name),
            },
        )

    @query(doc="names of the files matching a glob pattern, a size range and a modification time range")
    async def find(
        self, *, pattern: str = "", min_size: str = "", max_size: str = "", newer: str = "", older: str = ""
    ) -> list[str]:
        """Files by ``pattern`` (glob over the whole relative name), ``min_size``/``max_size`` (bytes)
        and ``newer``/``older`` (ISO 8601 times), sorted by name, at most :data:`MAX_LISTED`."""
        asked = FindQuery.parse(
            pattern=pattern, min_size=min_size, max_size=max_size, newer=newer, older=older
        )
        shown = self._shown

        def keep(info: FileInfo) -> bool:
            return shown(info.name) and asked.matches(info)

        found, _ = await self._disk(self._folder.scan, keep, MAX_LISTED)
        return [f.name for f in found]

    # -- the live list of files ----------------------------------------------------

    async def _refresh(self) -> None:
        """Read the list of files again (one reading at a time; asked again meanwhile: once more)."""
        if self._refreshing:
            self._refresh_again = True
            return
        self._refreshing = True
        try:
            while True:
                self._refresh_again = False
                try:
                    found, truncated = await self._disk(self._folder.scan, self._listable, MAX_LISTED)
                except Unavailable as exc:  # the directory itself is gone: no files until it is back
                    log.warning("%s", exc.message)
                    found, truncated = [], False
                if truncated and not self._warned_truncated:
                    self._warned_truncated = True
                    log.warning(
                        "%s holds more than %d files: `files` lists %d; use find",
                        self._root,
                        MAX_LISTED,
                        MAX_LISTED,
                    )
                names = [f.name for f in found]
                if names != self.files:
                    self.files = names
                if not self._refresh_again:
                    return
        finally:
            self._refreshing = False

    def _listable(self, info: FileInfo) -> bool:
        return self._shown(info.name)

    def _listed(self, name: str, present: bool) -> None:
        """Our own store or removal of ``name``: ``files`` follows at once, not after the watch."""
        files = self.files
        if present and name not in files and len(files) < MAX_LISTED:
            self.files = sorted([*files, name])
        elif not present and name in files:
            self.files = [f for f in files if f != name]

    def _on_disk(self, changed: dict[str, bool] | None) -> None:
        """The watcher's report: follow what changed (None: anything may have)."""
        if changed is None:
            relist = True
            touched = list(self._followed.values())
        else:
            known = set(self.files)
            relist = any(deleted or name not in known for name, deleted in changed.items())
            touched = [
                entry
                for entry in self._followed.values()
                if any(entry.name == name or entry.name.startswith(name + "/") for name in changed)
            ]
        if relist:
            self._ps_spawn(self._refresh(), "list files")
        for entry in touched:
            self._ps_spawn(self._reread(entry), f"read {entry.name}")

    # -- following files -----------------------------------------------------------

    async def follow(self, name: str, notify: Notify, prop: str = FILE) -> Subscription:
        """Call ``notify`` with ``Change(prop, content)`` whenever file ``name`` changes (what a Listen
        of ``file``, text, or ``blob``, bytes, does); ``Change(removed=True)`` when it is removed,
        its content again when it is back."""
        self._readable(name)
        key = (name, prop)
        entry = self._followed.get(key)
        if entry is None:
            if len(self._followed) >= MAX_FOLLOWED:
                raise ResourceExhausted(f"cannot follow `{name}`: {MAX_FOLLOWED} files are followed already")
            entry = self._followed[key] = _Followed(name, prop)
            entry.reading = True
            try:
                entry.last = await self._state(name, prop)
            except BaseException:
                if not entry.listeners and self._followed.get(key) is entry:
                    del self._followed[key]
                raise
            finally:
                entry.reading = False
            if entry.again:
                self._ps_spawn(self._reread(entry), f"read {name}")
        token = next(self._tokens)
        entry.listeners[token] = notify
        return _FileSubscription(self, entry, token)

    def _unfollow(self, entry: _Followed, token: int) -> None:
        gone = entry.listeners.pop(token, None) is not None and not entry.listeners
        key = (entry.name, entry.prop)
        if gone and self._followed.get(key) is entry:
            del self._followed[key]

    async def _state(self, name: str, prop: str) -> _State:
        try:
            data = await self._disk(self._folder.read, name, self.max_file_size)
            return data if prop == BLOB else _text(name, data)
        except NotFound:
            return None
        except PropertyError as exc:
            log.debug("%s: not followed through %s: %s", name, prop, exc.message)
            return _UNREADABLE

    async def _reread(self, entry: _Followed) -> None:
        if entry.reading:
            entry.again = True
            return
        entry.reading = True
        try:
            while True:
                entry.again = False
                state = await self._state(entry.name, entry.prop)
                self._deliver(entry, state)
                if not entry.again:
                    return
        finally:
            entry.reading = False

    def _stored(self, name: str, data: bytes | None) -> None:
        """Our own store (``data``) or removal (None) of ``name``: its followers hear it at once."""
        self._listed(name, data is not None)
        blob = self._followed.get((name, BLOB))
        if blob is not None:
            self._deliver(blob, data)
        text = self._followed.get((name, FILE))
        if text is not None:
            state: _State = data
            if data is not None:
                try:
                    state = data.decode("utf-8")
                except UnicodeDecodeError:
                    state = _UNREADABLE
            self._deliver(text, state)

    def _deliver(self, entry: _Followed, state: _State) -> None:
        if state == entry.last:
            return
        entry.last = state
        if isinstance(state, _Unreadable):
            return  # nothing the property can carry; the next content is heard
        change = Change(entry.prop, "", removed=True) if state is None else Change(entry.prop, state)
        # Kept on a raise: the listener's close takes it out, and the last one's ends the follow.
        tell_each(entry.listeners, change, what=f"file {entry.name}", on_raise=OnRaise.KEEP)


def _everything(name: str) -> bool:
    return True


def _text(name: str, data: bytes) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise FailedPrecondition(
            f"`{name}` is not UTF-8 text ({len(data)} bytes): read it as bytes with `blob` "
            f"(parameter name={name}), of media type {media_type(name)}"
        ) from None


def _too_big(name: str, size: int, limit: int) -> ResourceExhausted:
    return ResourceExhausted(
        f"cannot store `{name}`: {size} bytes, over the limit of {limit} bytes (max_file_size)"
    )
