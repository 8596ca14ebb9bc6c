from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Relation(_message.Message):
    __slots__ = ("predicate", "target", "anchor")
    PREDICATE_FIELD_NUMBER: _ClassVar[int]
    TARGET_FIELD_NUMBER: _ClassVar[int]
    ANCHOR_FIELD_NUMBER: _ClassVar[int]
    predicate: str
    target: str
    anchor: str
    def __init__(self, predicate: _Optional[str] = ..., target: _Optional[str] = ..., anchor: _Optional[str] = ...) -> None: ...

class TaskGraph(_message.Message):
    __slots__ = ("targets", "anchors", "relations", "unsupported", "backend", "warnings")
    TARGETS_FIELD_NUMBER: _ClassVar[int]
    ANCHORS_FIELD_NUMBER: _ClassVar[int]
    RELATIONS_FIELD_NUMBER: _ClassVar[int]
    UNSUPPORTED_FIELD_NUMBER: _ClassVar[int]
    BACKEND_FIELD_NUMBER: _ClassVar[int]
    WARNINGS_FIELD_NUMBER: _ClassVar[int]
    targets: _containers.RepeatedScalarFieldContainer[str]
    anchors: _containers.RepeatedScalarFieldContainer[str]
    relations: _containers.RepeatedCompositeFieldContainer[Relation]
    unsupported: _containers.RepeatedScalarFieldContainer[str]
    backend: str
    warnings: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, targets: _Optional[_Iterable[str]] = ..., anchors: _Optional[_Iterable[str]] = ..., relations: _Optional[_Iterable[_Union[Relation, _Mapping]]] = ..., unsupported: _Optional[_Iterable[str]] = ..., backend: _Optional[str] = ..., warnings: _Optional[_Iterable[str]] = ...) -> None: ...
