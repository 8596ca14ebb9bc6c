from gausslite_rpc import common_pb2 as _common_pb2
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class ParseRequest(_message.Message):
    __slots__ = ("task_text",)
    TASK_TEXT_FIELD_NUMBER: _ClassVar[int]
    task_text: str
    def __init__(self, task_text: _Optional[str] = ...) -> None: ...
