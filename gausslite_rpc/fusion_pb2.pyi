from gausslite_rpc import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class FuseMethod(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FUSE_METHOD_UNSPECIFIED: _ClassVar[FuseMethod]
    FUSE_METHOD_VOTE: _ClassVar[FuseMethod]
    FUSE_METHOD_CONCAT: _ClassVar[FuseMethod]
FUSE_METHOD_UNSPECIFIED: FuseMethod
FUSE_METHOD_VOTE: FuseMethod
FUSE_METHOD_CONCAT: FuseMethod

class OpenSessionRequest(_message.Message):
    __slots__ = ("agent_id", "task_text", "intrinsics")
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    TASK_TEXT_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    task_text: str
    intrinsics: _common_pb2.Intrinsics
    def __init__(self, agent_id: _Optional[str] = ..., task_text: _Optional[str] = ..., intrinsics: _Optional[_Union[_common_pb2.Intrinsics, _Mapping]] = ...) -> None: ...

class SessionInfo(_message.Message):
    __slots__ = ("agent_id", "created", "latest_map_version", "has_complete_subset", "keyframes", "max_keyframes", "max_message_bytes", "max_chunk_bytes", "max_chunk_gaussians", "max_subset_gaussians", "max_chunks")
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    CREATED_FIELD_NUMBER: _ClassVar[int]
    LATEST_MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    HAS_COMPLETE_SUBSET_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    MAX_KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    MAX_MESSAGE_BYTES_FIELD_NUMBER: _ClassVar[int]
    MAX_CHUNK_BYTES_FIELD_NUMBER: _ClassVar[int]
    MAX_CHUNK_GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    MAX_SUBSET_GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    MAX_CHUNKS_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    created: bool
    latest_map_version: int
    has_complete_subset: bool
    keyframes: int
    max_keyframes: int
    max_message_bytes: int
    max_chunk_bytes: int
    max_chunk_gaussians: int
    max_subset_gaussians: int
    max_chunks: int
    def __init__(self, agent_id: _Optional[str] = ..., created: _Optional[bool] = ..., latest_map_version: _Optional[int] = ..., has_complete_subset: _Optional[bool] = ..., keyframes: _Optional[int] = ..., max_keyframes: _Optional[int] = ..., max_message_bytes: _Optional[int] = ..., max_chunk_bytes: _Optional[int] = ..., max_chunk_gaussians: _Optional[int] = ..., max_subset_gaussians: _Optional[int] = ..., max_chunks: _Optional[int] = ...) -> None: ...

class UploadHeader(_message.Message):
    __slots__ = ("agent_id", "map_version", "n_chunks", "full_map_gaussians", "full_map_bytes")
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    N_CHUNKS_FIELD_NUMBER: _ClassVar[int]
    FULL_MAP_GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    FULL_MAP_BYTES_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    map_version: int
    n_chunks: int
    full_map_gaussians: int
    full_map_bytes: int
    def __init__(self, agent_id: _Optional[str] = ..., map_version: _Optional[int] = ..., n_chunks: _Optional[int] = ..., full_map_gaussians: _Optional[int] = ..., full_map_bytes: _Optional[int] = ...) -> None: ...

class UploadSubsetRequest(_message.Message):
    __slots__ = ("header", "chunk")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    CHUNK_FIELD_NUMBER: _ClassVar[int]
    header: UploadHeader
    chunk: bytes
    def __init__(self, header: _Optional[_Union[UploadHeader, _Mapping]] = ..., chunk: _Optional[bytes] = ...) -> None: ...

class UploadStatusRequest(_message.Message):
    __slots__ = ("agent_id", "map_version")
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    map_version: int
    def __init__(self, agent_id: _Optional[str] = ..., map_version: _Optional[int] = ...) -> None: ...

class UploadAck(_message.Message):
    __slots__ = ("agent_id", "map_version", "n_chunks", "stored", "missing", "complete", "newly_stored", "n_gaussians", "bytes_on_wire", "is_latest", "superseded_by", "stored_bytes")
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    N_CHUNKS_FIELD_NUMBER: _ClassVar[int]
    STORED_FIELD_NUMBER: _ClassVar[int]
    MISSING_FIELD_NUMBER: _ClassVar[int]
    COMPLETE_FIELD_NUMBER: _ClassVar[int]
    NEWLY_STORED_FIELD_NUMBER: _ClassVar[int]
    N_GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    BYTES_ON_WIRE_FIELD_NUMBER: _ClassVar[int]
    IS_LATEST_FIELD_NUMBER: _ClassVar[int]
    SUPERSEDED_BY_FIELD_NUMBER: _ClassVar[int]
    STORED_BYTES_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    map_version: int
    n_chunks: int
    stored: _containers.RepeatedScalarFieldContainer[int]
    missing: _containers.RepeatedScalarFieldContainer[int]
    complete: bool
    newly_stored: int
    n_gaussians: int
    bytes_on_wire: int
    is_latest: bool
    superseded_by: int
    stored_bytes: int
    def __init__(self, agent_id: _Optional[str] = ..., map_version: _Optional[int] = ..., n_chunks: _Optional[int] = ..., stored: _Optional[_Iterable[int]] = ..., missing: _Optional[_Iterable[int]] = ..., complete: _Optional[bool] = ..., newly_stored: _Optional[int] = ..., n_gaussians: _Optional[int] = ..., bytes_on_wire: _Optional[int] = ..., is_latest: _Optional[bool] = ..., superseded_by: _Optional[int] = ..., stored_bytes: _Optional[int] = ...) -> None: ...

class KeyframeRequest(_message.Message):
    __slots__ = ("agent_id", "frame_id", "color", "depth_png", "depth_scale", "pose", "intrinsics", "timestamp", "roi_png")
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    COLOR_FIELD_NUMBER: _ClassVar[int]
    DEPTH_PNG_FIELD_NUMBER: _ClassVar[int]
    DEPTH_SCALE_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_FIELD_NUMBER: _ClassVar[int]
    ROI_PNG_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    frame_id: int
    color: bytes
    depth_png: bytes
    depth_scale: float
    pose: _common_pb2.Pose
    intrinsics: _common_pb2.Intrinsics
    timestamp: float
    roi_png: bytes
    def __init__(self, agent_id: _Optional[str] = ..., frame_id: _Optional[int] = ..., color: _Optional[bytes] = ..., depth_png: _Optional[bytes] = ..., depth_scale: _Optional[float] = ..., pose: _Optional[_Union[_common_pb2.Pose, _Mapping]] = ..., intrinsics: _Optional[_Union[_common_pb2.Intrinsics, _Mapping]] = ..., timestamp: _Optional[float] = ..., roi_png: _Optional[bytes] = ...) -> None: ...

class KeyframeAck(_message.Message):
    __slots__ = ("agent_id", "received", "stored", "duplicates", "evicted", "buffered")
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    RECEIVED_FIELD_NUMBER: _ClassVar[int]
    STORED_FIELD_NUMBER: _ClassVar[int]
    DUPLICATES_FIELD_NUMBER: _ClassVar[int]
    EVICTED_FIELD_NUMBER: _ClassVar[int]
    BUFFERED_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    received: int
    stored: int
    duplicates: int
    evicted: int
    buffered: int
    def __init__(self, agent_id: _Optional[str] = ..., received: _Optional[int] = ..., stored: _Optional[int] = ..., duplicates: _Optional[int] = ..., evicted: _Optional[int] = ..., buffered: _Optional[int] = ...) -> None: ...

class FuseRequest(_message.Message):
    __slots__ = ("method", "voxel_size", "refine", "refine_iters", "seed", "contest_radius", "for_agent", "team_map")
    METHOD_FIELD_NUMBER: _ClassVar[int]
    VOXEL_SIZE_FIELD_NUMBER: _ClassVar[int]
    REFINE_FIELD_NUMBER: _ClassVar[int]
    REFINE_ITERS_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    CONTEST_RADIUS_FIELD_NUMBER: _ClassVar[int]
    FOR_AGENT_FIELD_NUMBER: _ClassVar[int]
    TEAM_MAP_FIELD_NUMBER: _ClassVar[int]
    method: FuseMethod
    voxel_size: float
    refine: bool
    refine_iters: int
    seed: int
    contest_radius: int
    for_agent: str
    team_map: bool
    def __init__(self, method: _Optional[_Union[FuseMethod, str]] = ..., voxel_size: _Optional[float] = ..., refine: _Optional[bool] = ..., refine_iters: _Optional[int] = ..., seed: _Optional[int] = ..., contest_radius: _Optional[int] = ..., for_agent: _Optional[str] = ..., team_map: _Optional[bool] = ...) -> None: ...

class RefineRecord(_message.Message):
    __slots__ = ("iters_requested", "iters_planned", "iters_run", "train_views", "heldout_views", "validated", "vote_loss", "best_loss", "best_iter", "stopped_early", "rolled_back")
    ITERS_REQUESTED_FIELD_NUMBER: _ClassVar[int]
    ITERS_PLANNED_FIELD_NUMBER: _ClassVar[int]
    ITERS_RUN_FIELD_NUMBER: _ClassVar[int]
    TRAIN_VIEWS_FIELD_NUMBER: _ClassVar[int]
    HELDOUT_VIEWS_FIELD_NUMBER: _ClassVar[int]
    VALIDATED_FIELD_NUMBER: _ClassVar[int]
    VOTE_LOSS_FIELD_NUMBER: _ClassVar[int]
    BEST_LOSS_FIELD_NUMBER: _ClassVar[int]
    BEST_ITER_FIELD_NUMBER: _ClassVar[int]
    STOPPED_EARLY_FIELD_NUMBER: _ClassVar[int]
    ROLLED_BACK_FIELD_NUMBER: _ClassVar[int]
    iters_requested: int
    iters_planned: int
    iters_run: int
    train_views: int
    heldout_views: int
    validated: bool
    vote_loss: float
    best_loss: float
    best_iter: int
    stopped_early: bool
    rolled_back: bool
    def __init__(self, iters_requested: _Optional[int] = ..., iters_planned: _Optional[int] = ..., iters_run: _Optional[int] = ..., train_views: _Optional[int] = ..., heldout_views: _Optional[int] = ..., validated: _Optional[bool] = ..., vote_loss: _Optional[float] = ..., best_loss: _Optional[float] = ..., best_iter: _Optional[int] = ..., stopped_early: _Optional[bool] = ..., rolled_back: _Optional[bool] = ...) -> None: ...

class AgentContribution(_message.Message):
    __slots__ = ("agent_id", "map_version", "received", "kept", "first_row")
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    RECEIVED_FIELD_NUMBER: _ClassVar[int]
    KEPT_FIELD_NUMBER: _ClassVar[int]
    FIRST_ROW_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    map_version: int
    received: int
    kept: int
    first_row: int
    def __init__(self, agent_id: _Optional[str] = ..., map_version: _Optional[int] = ..., received: _Optional[int] = ..., kept: _Optional[int] = ..., first_row: _Optional[int] = ...) -> None: ...

class FuseResult(_message.Message):
    __slots__ = ("fused_version", "n_gaussians", "seconds", "agents", "method", "refined", "refine_iters", "voxel_size", "keyframes_used", "bytes", "created_unix", "vote_seconds", "agents_revoted", "incremental", "contest_radius", "for_agent", "refine_record", "team_map", "age_s", "team_map_current", "keyframes_seen")
    FUSED_VERSION_FIELD_NUMBER: _ClassVar[int]
    N_GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    SECONDS_FIELD_NUMBER: _ClassVar[int]
    AGENTS_FIELD_NUMBER: _ClassVar[int]
    METHOD_FIELD_NUMBER: _ClassVar[int]
    REFINED_FIELD_NUMBER: _ClassVar[int]
    REFINE_ITERS_FIELD_NUMBER: _ClassVar[int]
    VOXEL_SIZE_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_USED_FIELD_NUMBER: _ClassVar[int]
    BYTES_FIELD_NUMBER: _ClassVar[int]
    CREATED_UNIX_FIELD_NUMBER: _ClassVar[int]
    VOTE_SECONDS_FIELD_NUMBER: _ClassVar[int]
    AGENTS_REVOTED_FIELD_NUMBER: _ClassVar[int]
    INCREMENTAL_FIELD_NUMBER: _ClassVar[int]
    CONTEST_RADIUS_FIELD_NUMBER: _ClassVar[int]
    FOR_AGENT_FIELD_NUMBER: _ClassVar[int]
    REFINE_RECORD_FIELD_NUMBER: _ClassVar[int]
    TEAM_MAP_FIELD_NUMBER: _ClassVar[int]
    AGE_S_FIELD_NUMBER: _ClassVar[int]
    TEAM_MAP_CURRENT_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_SEEN_FIELD_NUMBER: _ClassVar[int]
    fused_version: int
    n_gaussians: int
    seconds: float
    agents: _containers.RepeatedCompositeFieldContainer[AgentContribution]
    method: FuseMethod
    refined: bool
    refine_iters: int
    voxel_size: float
    keyframes_used: int
    bytes: int
    created_unix: float
    vote_seconds: float
    agents_revoted: int
    incremental: bool
    contest_radius: int
    for_agent: str
    refine_record: RefineRecord
    team_map: bool
    age_s: float
    team_map_current: bool
    keyframes_seen: int
    def __init__(self, fused_version: _Optional[int] = ..., n_gaussians: _Optional[int] = ..., seconds: _Optional[float] = ..., agents: _Optional[_Iterable[_Union[AgentContribution, _Mapping]]] = ..., method: _Optional[_Union[FuseMethod, str]] = ..., refined: _Optional[bool] = ..., refine_iters: _Optional[int] = ..., voxel_size: _Optional[float] = ..., keyframes_used: _Optional[int] = ..., bytes: _Optional[int] = ..., created_unix: _Optional[float] = ..., vote_seconds: _Optional[float] = ..., agents_revoted: _Optional[int] = ..., incremental: _Optional[bool] = ..., contest_radius: _Optional[int] = ..., for_agent: _Optional[str] = ..., refine_record: _Optional[_Union[RefineRecord, _Mapping]] = ..., team_map: _Optional[bool] = ..., age_s: _Optional[float] = ..., team_map_current: _Optional[bool] = ..., keyframes_seen: _Optional[int] = ...) -> None: ...

class FuseProgress(_message.Message):
    __slots__ = ("stage", "fraction", "message", "done", "result")
    STAGE_FIELD_NUMBER: _ClassVar[int]
    FRACTION_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    DONE_FIELD_NUMBER: _ClassVar[int]
    RESULT_FIELD_NUMBER: _ClassVar[int]
    stage: str
    fraction: float
    message: str
    done: bool
    result: FuseResult
    def __init__(self, stage: _Optional[str] = ..., fraction: _Optional[float] = ..., message: _Optional[str] = ..., done: _Optional[bool] = ..., result: _Optional[_Union[FuseResult, _Mapping]] = ...) -> None: ...

class DownloadFusedRequest(_message.Message):
    __slots__ = ("fused_version", "method")
    FUSED_VERSION_FIELD_NUMBER: _ClassVar[int]
    METHOD_FIELD_NUMBER: _ClassVar[int]
    fused_version: int
    method: FuseMethod
    def __init__(self, fused_version: _Optional[int] = ..., method: _Optional[_Union[FuseMethod, str]] = ...) -> None: ...

class FusedChunk(_message.Message):
    __slots__ = ("fused_version", "chunk_index", "n_chunks", "chunk", "info")
    FUSED_VERSION_FIELD_NUMBER: _ClassVar[int]
    CHUNK_INDEX_FIELD_NUMBER: _ClassVar[int]
    N_CHUNKS_FIELD_NUMBER: _ClassVar[int]
    CHUNK_FIELD_NUMBER: _ClassVar[int]
    INFO_FIELD_NUMBER: _ClassVar[int]
    fused_version: int
    chunk_index: int
    n_chunks: int
    chunk: bytes
    info: FuseResult
    def __init__(self, fused_version: _Optional[int] = ..., chunk_index: _Optional[int] = ..., n_chunks: _Optional[int] = ..., chunk: _Optional[bytes] = ..., info: _Optional[_Union[FuseResult, _Mapping]] = ...) -> None: ...

class StatsRequest(_message.Message):
    __slots__ = ("page_size", "page_token")
    PAGE_SIZE_FIELD_NUMBER: _ClassVar[int]
    PAGE_TOKEN_FIELD_NUMBER: _ClassVar[int]
    page_size: int
    page_token: str
    def __init__(self, page_size: _Optional[int] = ..., page_token: _Optional[str] = ...) -> None: ...

class AgentStats(_message.Message):
    __slots__ = ("agent_id", "task_text", "latest_map_version", "has_complete_subset", "gaussians_received", "bytes_on_wire", "chunks", "full_map_gaussians", "full_map_bytes", "share_pct", "keyframes", "bytes_per_gaussian", "stored_bytes")
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    TASK_TEXT_FIELD_NUMBER: _ClassVar[int]
    LATEST_MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    HAS_COMPLETE_SUBSET_FIELD_NUMBER: _ClassVar[int]
    GAUSSIANS_RECEIVED_FIELD_NUMBER: _ClassVar[int]
    BYTES_ON_WIRE_FIELD_NUMBER: _ClassVar[int]
    CHUNKS_FIELD_NUMBER: _ClassVar[int]
    FULL_MAP_GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    FULL_MAP_BYTES_FIELD_NUMBER: _ClassVar[int]
    SHARE_PCT_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    BYTES_PER_GAUSSIAN_FIELD_NUMBER: _ClassVar[int]
    STORED_BYTES_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    task_text: str
    latest_map_version: int
    has_complete_subset: bool
    gaussians_received: int
    bytes_on_wire: int
    chunks: int
    full_map_gaussians: int
    full_map_bytes: int
    share_pct: float
    keyframes: int
    bytes_per_gaussian: float
    stored_bytes: int
    def __init__(self, agent_id: _Optional[str] = ..., task_text: _Optional[str] = ..., latest_map_version: _Optional[int] = ..., has_complete_subset: _Optional[bool] = ..., gaussians_received: _Optional[int] = ..., bytes_on_wire: _Optional[int] = ..., chunks: _Optional[int] = ..., full_map_gaussians: _Optional[int] = ..., full_map_bytes: _Optional[int] = ..., share_pct: _Optional[float] = ..., keyframes: _Optional[int] = ..., bytes_per_gaussian: _Optional[float] = ..., stored_bytes: _Optional[int] = ...) -> None: ...

class StatsResponse(_message.Message):
    __slots__ = ("agents", "fused", "latest_fused_version", "next_page_token")
    AGENTS_FIELD_NUMBER: _ClassVar[int]
    FUSED_FIELD_NUMBER: _ClassVar[int]
    LATEST_FUSED_VERSION_FIELD_NUMBER: _ClassVar[int]
    NEXT_PAGE_TOKEN_FIELD_NUMBER: _ClassVar[int]
    agents: _containers.RepeatedCompositeFieldContainer[AgentStats]
    fused: _containers.RepeatedCompositeFieldContainer[FuseResult]
    latest_fused_version: int
    next_page_token: str
    def __init__(self, agents: _Optional[_Iterable[_Union[AgentStats, _Mapping]]] = ..., fused: _Optional[_Iterable[_Union[FuseResult, _Mapping]]] = ..., latest_fused_version: _Optional[int] = ..., next_page_token: _Optional[str] = ...) -> None: ...

class KeyframePosesRequest(_message.Message):
    __slots__ = ("agent_id",)
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    def __init__(self, agent_id: _Optional[str] = ...) -> None: ...

class KeyframePose(_message.Message):
    __slots__ = ("agent_id", "frame_id", "pose", "intrinsics", "timestamp")
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_FIELD_NUMBER: _ClassVar[int]
    agent_id: str
    frame_id: int
    pose: _common_pb2.Pose
    intrinsics: _common_pb2.Intrinsics
    timestamp: float
    def __init__(self, agent_id: _Optional[str] = ..., frame_id: _Optional[int] = ..., pose: _Optional[_Union[_common_pb2.Pose, _Mapping]] = ..., intrinsics: _Optional[_Union[_common_pb2.Intrinsics, _Mapping]] = ..., timestamp: _Optional[float] = ...) -> None: ...

class KeyframePosesResponse(_message.Message):
    __slots__ = ("keyframes",)
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    keyframes: _containers.RepeatedCompositeFieldContainer[KeyframePose]
    def __init__(self, keyframes: _Optional[_Iterable[_Union[KeyframePose, _Mapping]]] = ...) -> None: ...
