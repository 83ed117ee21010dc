import datetime

from google.protobuf import duration_pb2 as _duration_pb2
from google.protobuf import timestamp_pb2 as _timestamp_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Access(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ACCESS_UNKNOWN: _ClassVar[Access]
    ACCESS_READ: _ClassVar[Access]
    ACCESS_WRITE: _ClassVar[Access]
    ACCESS_READ_WRITE: _ClassVar[Access]
    ACCESS_ACTION: _ClassVar[Access]
    ACCESS_QUERY: _ClassVar[Access]
ACCESS_UNKNOWN: Access
ACCESS_READ: Access
ACCESS_WRITE: Access
ACCESS_READ_WRITE: Access
ACCESS_ACTION: Access
ACCESS_QUERY: Access

class PropertyRef(_message.Message):
    __slots__ = ("service", "property", "parameters")
    class ParametersEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    PROPERTY_FIELD_NUMBER: _ClassVar[int]
    PARAMETERS_FIELD_NUMBER: _ClassVar[int]
    service: str
    property: str
    parameters: _containers.ScalarMap[str, str]
    def __init__(self, service: _Optional[str] = ..., property: _Optional[str] = ..., parameters: _Optional[_Mapping[str, str]] = ...) -> None: ...

class GetRequest(_message.Message):
    __slots__ = ("service", "property", "parameters", "more")
    class ParametersEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    PROPERTY_FIELD_NUMBER: _ClassVar[int]
    PARAMETERS_FIELD_NUMBER: _ClassVar[int]
    MORE_FIELD_NUMBER: _ClassVar[int]
    service: str
    property: str
    parameters: _containers.ScalarMap[str, str]
    more: _containers.RepeatedCompositeFieldContainer[PropertyRef]
    def __init__(self, service: _Optional[str] = ..., property: _Optional[str] = ..., parameters: _Optional[_Mapping[str, str]] = ..., more: _Optional[_Iterable[_Union[PropertyRef, _Mapping]]] = ...) -> None: ...

class GetResponse(_message.Message):
    __slots__ = ("value", "more", "data", "time")
    VALUE_FIELD_NUMBER: _ClassVar[int]
    MORE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    value: str
    more: _containers.RepeatedCompositeFieldContainer[PropertyValue]
    data: bytes
    time: _timestamp_pb2.Timestamp
    def __init__(self, value: _Optional[str] = ..., more: _Optional[_Iterable[_Union[PropertyValue, _Mapping]]] = ..., data: _Optional[bytes] = ..., time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ...) -> None: ...

class PropertyValue(_message.Message):
    __slots__ = ("service", "property", "value", "data", "time")
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    PROPERTY_FIELD_NUMBER: _ClassVar[int]
    VALUE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    service: str
    property: str
    value: str
    data: bytes
    time: _timestamp_pb2.Timestamp
    def __init__(self, service: _Optional[str] = ..., property: _Optional[str] = ..., value: _Optional[str] = ..., data: _Optional[bytes] = ..., time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ...) -> None: ...

class SetRequest(_message.Message):
    __slots__ = ("service", "property", "parameters", "value", "data")
    class ParametersEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    PROPERTY_FIELD_NUMBER: _ClassVar[int]
    PARAMETERS_FIELD_NUMBER: _ClassVar[int]
    VALUE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    service: str
    property: str
    parameters: _containers.ScalarMap[str, str]
    value: str
    data: bytes
    def __init__(self, service: _Optional[str] = ..., property: _Optional[str] = ..., parameters: _Optional[_Mapping[str, str]] = ..., value: _Optional[str] = ..., data: _Optional[bytes] = ...) -> None: ...

class SetResponse(_message.Message):
    __slots__ = ("value", "data")
    VALUE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    value: str
    data: bytes
    def __init__(self, value: _Optional[str] = ..., data: _Optional[bytes] = ...) -> None: ...

class ListenOptions(_message.Message):
    __slots__ = ("updates_only", "min_interval", "sample_interval", "heartbeat_interval", "max_batch")
    UPDATES_ONLY_FIELD_NUMBER: _ClassVar[int]
    MIN_INTERVAL_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_INTERVAL_FIELD_NUMBER: _ClassVar[int]
    HEARTBEAT_INTERVAL_FIELD_NUMBER: _ClassVar[int]
    MAX_BATCH_FIELD_NUMBER: _ClassVar[int]
    updates_only: bool
    min_interval: _duration_pb2.Duration
    sample_interval: _duration_pb2.Duration
    heartbeat_interval: _duration_pb2.Duration
    max_batch: int
    def __init__(self, updates_only: _Optional[bool] = ..., min_interval: _Optional[_Union[datetime.timedelta, _duration_pb2.Duration, _Mapping]] = ..., sample_interval: _Optional[_Union[datetime.timedelta, _duration_pb2.Duration, _Mapping]] = ..., heartbeat_interval: _Optional[_Union[datetime.timedelta, _duration_pb2.Duration, _Mapping]] = ..., max_batch: _Optional[int] = ...) -> None: ...

class ListenRequest(_message.Message):
    __slots__ = ("service", "property", "parameters", "more", "options")
    class ParametersEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    PROPERTY_FIELD_NUMBER: _ClassVar[int]
    PARAMETERS_FIELD_NUMBER: _ClassVar[int]
    MORE_FIELD_NUMBER: _ClassVar[int]
    OPTIONS_FIELD_NUMBER: _ClassVar[int]
    service: str
    property: str
    parameters: _containers.ScalarMap[str, str]
    more: _containers.RepeatedCompositeFieldContainer[PropertyRef]
    options: ListenOptions
    def __init__(self, service: _Optional[str] = ..., property: _Optional[str] = ..., parameters: _Optional[_Mapping[str, str]] = ..., more: _Optional[_Iterable[_Union[PropertyRef, _Mapping]]] = ..., options: _Optional[_Union[ListenOptions, _Mapping]] = ...) -> None: ...

class Event(_message.Message):
    __slots__ = ("service", "property", "value", "sequence", "time", "conflated", "gap", "removed", "data")
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    PROPERTY_FIELD_NUMBER: _ClassVar[int]
    VALUE_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    CONFLATED_FIELD_NUMBER: _ClassVar[int]
    GAP_FIELD_NUMBER: _ClassVar[int]
    REMOVED_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    service: str
    property: str
    value: str
    sequence: int
    time: _timestamp_pb2.Timestamp
    conflated: int
    gap: bool
    removed: bool
    data: bytes
    def __init__(self, service: _Optional[str] = ..., property: _Optional[str] = ..., value: _Optional[str] = ..., sequence: _Optional[int] = ..., time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., conflated: _Optional[int] = ..., gap: _Optional[bool] = ..., removed: _Optional[bool] = ..., data: _Optional[bytes] = ...) -> None: ...

class ListenResponse(_message.Message):
    __slots__ = ("events", "sync", "heartbeat")
    EVENTS_FIELD_NUMBER: _ClassVar[int]
    SYNC_FIELD_NUMBER: _ClassVar[int]
    HEARTBEAT_FIELD_NUMBER: _ClassVar[int]
    events: _containers.RepeatedCompositeFieldContainer[Event]
    sync: bool
    heartbeat: bool
    def __init__(self, events: _Optional[_Iterable[_Union[Event, _Mapping]]] = ..., sync: _Optional[bool] = ..., heartbeat: _Optional[bool] = ...) -> None: ...

class Status(_message.Message):
    __slots__ = ("code", "message")
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    code: int
    message: str
    def __init__(self, code: _Optional[int] = ..., message: _Optional[str] = ...) -> None: ...

class Cancel(_message.Message):
    __slots__ = ("id",)
    ID_FIELD_NUMBER: _ClassVar[int]
    id: int
    def __init__(self, id: _Optional[int] = ...) -> None: ...

class Request(_message.Message):
    __slots__ = ("id", "get", "set", "listen", "cancel")
    ID_FIELD_NUMBER: _ClassVar[int]
    GET_FIELD_NUMBER: _ClassVar[int]
    SET_FIELD_NUMBER: _ClassVar[int]
    LISTEN_FIELD_NUMBER: _ClassVar[int]
    CANCEL_FIELD_NUMBER: _ClassVar[int]
    id: int
    get: GetRequest
    set: SetRequest
    listen: ListenRequest
    cancel: Cancel
    def __init__(self, id: _Optional[int] = ..., get: _Optional[_Union[GetRequest, _Mapping]] = ..., set: _Optional[_Union[SetRequest, _Mapping]] = ..., listen: _Optional[_Union[ListenRequest, _Mapping]] = ..., cancel: _Optional[_Union[Cancel, _Mapping]] = ...) -> None: ...

class Reply(_message.Message):
    __slots__ = ("id", "status", "get", "set", "listen")
    ID_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    GET_FIELD_NUMBER: _ClassVar[int]
    SET_FIELD_NUMBER: _ClassVar[int]
    LISTEN_FIELD_NUMBER: _ClassVar[int]
    id: int
    status: Status
    get: GetResponse
    set: SetResponse
    listen: ListenResponse
    def __init__(self, id: _Optional[int] = ..., status: _Optional[_Union[Status, _Mapping]] = ..., get: _Optional[_Union[GetResponse, _Mapping]] = ..., set: _Optional[_Union[SetResponse, _Mapping]] = ..., listen: _Optional[_Union[ListenResponse, _Mapping]] = ...) -> None: ...

class SessionRequest(_message.Message):
    __slots__ = ("requests",)
    REQUESTS_FIELD_NUMBER: _ClassVar[int]
    requests: _containers.RepeatedCompositeFieldContainer[Request]
    def __init__(self, requests: _Optional[_Iterable[_Union[Request, _Mapping]]] = ...) -> None: ...

class SessionResponse(_message.Message):
    __slots__ = ("replies",)
    REPLIES_FIELD_NUMBER: _ClassVar[int]
    replies: _containers.RepeatedCompositeFieldContainer[Reply]
    def __init__(self, replies: _Optional[_Iterable[_Union[Reply, _Mapping]]] = ...) -> None: ...

class DescribeRequest(_message.Message):
    __slots__ = ("service",)
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    service: str
    def __init__(self, service: _Optional[str] = ...) -> None: ...

class DescribeResponse(_message.Message):
    __slots__ = ("type", "properties", "doc")
    TYPE_FIELD_NUMBER: _ClassVar[int]
    PROPERTIES_FIELD_NUMBER: _ClassVar[int]
    DOC_FIELD_NUMBER: _ClassVar[int]
    type: str
    properties: _containers.RepeatedCompositeFieldContainer[PropertyInfo]
    doc: str
    def __init__(self, type: _Optional[str] = ..., properties: _Optional[_Iterable[_Union[PropertyInfo, _Mapping]]] = ..., doc: _Optional[str] = ...) -> None: ...

class PropertyInfo(_message.Message):
    __slots__ = ("name", "type", "access", "length", "unit", "minimum", "maximum", "choices", "doc", "gui", "value", "parameters", "media_type", "max_size", "resolution")
    NAME_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    ACCESS_FIELD_NUMBER: _ClassVar[int]
    LENGTH_FIELD_NUMBER: _ClassVar[int]
    UNIT_FIELD_NUMBER: _ClassVar[int]
    MINIMUM_FIELD_NUMBER: _ClassVar[int]
    MAXIMUM_FIELD_NUMBER: _ClassVar[int]
    CHOICES_FIELD_NUMBER: _ClassVar[int]
    DOC_FIELD_NUMBER: _ClassVar[int]
    GUI_FIELD_NUMBER: _ClassVar[int]
    VALUE_FIELD_NUMBER: _ClassVar[int]
    PARAMETERS_FIELD_NUMBER: _ClassVar[int]
    MEDIA_TYPE_FIELD_NUMBER: _ClassVar[int]
    MAX_SIZE_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    name: str
    type: str
    access: Access
    length: int
    unit: str
    minimum: float
    maximum: float
    choices: _containers.RepeatedScalarFieldContainer[str]
    doc: str
    gui: str
    value: ParameterInfo
    parameters: _containers.RepeatedCompositeFieldContainer[ParameterInfo]
    media_type: str
    max_size: int
    resolution: float
    def __init__(self, name: _Optional[str] = ..., type: _Optional[str] = ..., access: _Optional[_Union[Access, str]] = ..., length: _Optional[int] = ..., unit: _Optional[str] = ..., minimum: _Optional[float] = ..., maximum: _Optional[float] = ..., choices: _Optional[_Iterable[str]] = ..., doc: _Optional[str] = ..., gui: _Optional[str] = ..., value: _Optional[_Union[ParameterInfo, _Mapping]] = ..., parameters: _Optional[_Iterable[_Union[ParameterInfo, _Mapping]]] = ..., media_type: _Optional[str] = ..., max_size: _Optional[int] = ..., resolution: _Optional[float] = ...) -> None: ...

class ParameterInfo(_message.Message):
    __slots__ = ("name", "type", "required", "default", "doc")
    NAME_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    REQUIRED_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_FIELD_NUMBER: _ClassVar[int]
    DOC_FIELD_NUMBER: _ClassVar[int]
    name: str
    type: str
    required: bool
    default: str
    doc: str
    def __init__(self, name: _Optional[str] = ..., type: _Optional[str] = ..., required: _Optional[bool] = ..., default: _Optional[str] = ..., doc: _Optional[str] = ...) -> None: ...

class HistoryRequest(_message.Message):
    __slots__ = ("service", "property", "since", "until", "limit")
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    PROPERTY_FIELD_NUMBER: _ClassVar[int]
    SINCE_FIELD_NUMBER: _ClassVar[int]
    UNTIL_FIELD_NUMBER: _ClassVar[int]
    LIMIT_FIELD_NUMBER: _ClassVar[int]
    service: str
    property: str
    since: _timestamp_pb2.Timestamp
    until: _timestamp_pb2.Timestamp
    limit: int
    def __init__(self, service: _Optional[str] = ..., property: _Optional[str] = ..., since: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., until: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., limit: _Optional[int] = ...) -> None: ...

class HistoryResponse(_message.Message):
    __slots__ = ("events", "truncated")
    EVENTS_FIELD_NUMBER: _ClassVar[int]
    TRUNCATED_FIELD_NUMBER: _ClassVar[int]
    events: _containers.RepeatedCompositeFieldContainer[Event]
    truncated: bool
    def __init__(self, events: _Optional[_Iterable[_Union[Event, _Mapping]]] = ..., truncated: _Optional[bool] = ...) -> None: ...
