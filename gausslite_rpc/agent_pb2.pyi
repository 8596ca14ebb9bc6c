from gausslite_rpc import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class MissionState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    MISSION_STATE_UNSPECIFIED: _ClassVar[MissionState]
    MISSION_STATE_MAPPING: _ClassVar[MissionState]
    MISSION_STATE_REPLAY_DONE: _ClassVar[MissionState]
    MISSION_STATE_FINISHING: _ClassVar[MissionState]
    MISSION_STATE_FINISHED: _ClassVar[MissionState]
    MISSION_STATE_FAILED: _ClassVar[MissionState]
MISSION_STATE_UNSPECIFIED: MissionState
MISSION_STATE_MAPPING: MissionState
MISSION_STATE_REPLAY_DONE: MissionState
MISSION_STATE_FINISHING: MissionState
MISSION_STATE_FINISHED: MissionState
MISSION_STATE_FAILED: MissionState

class StartMissionRequest(_message.Message):
    __slots__ = ("task_text", "task_id", "dataset_path", "annotations_path", "fusion_address", "agent_id", "mission_id", "T_world_map")
    TASK_TEXT_FIELD_NUMBER: _ClassVar[int]
    TASK_ID_FIELD_NUMBER: _ClassVar[int]
    DATASET_PATH_FIELD_NUMBER: _ClassVar[int]
    ANNOTATIONS_PATH_FIELD_NUMBER: _ClassVar[int]
    FUSION_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    MISSION_ID_FIELD_NUMBER: _ClassVar[int]
    T_WORLD_MAP_FIELD_NUMBER: _ClassVar[int]
    task_text: str
    task_id: str
    dataset_path: str
    annotations_path: str
    fusion_address: str
    agent_id: str
    mission_id: str
    T_world_map: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, task_text: _Optional[str] = ..., task_id: _Optional[str] = ..., dataset_path: _Optional[str] = ..., annotations_path: _Optional[str] = ..., fusion_address: _Optional[str] = ..., agent_id: _Optional[str] = ..., mission_id: _Optional[str] = ..., T_world_map: _Optional[_Iterable[float]] = ...) -> None: ...

class UpdateTaskRequest(_message.Message):
    __slots__ = ("mission_id", "task_text", "task_id")
    MISSION_ID_FIELD_NUMBER: _ClassVar[int]
    TASK_TEXT_FIELD_NUMBER: _ClassVar[int]
    TASK_ID_FIELD_NUMBER: _ClassVar[int]
    mission_id: str
    task_text: str
    task_id: str
    def __init__(self, mission_id: _Optional[str] = ..., task_text: _Optional[str] = ..., task_id: _Optional[str] = ...) -> None: ...

class UpdateTaskResponse(_message.Message):
    __slots__ = ("mission_id", "graph")
    MISSION_ID_FIELD_NUMBER: _ClassVar[int]
    GRAPH_FIELD_NUMBER: _ClassVar[int]
    mission_id: str
    graph: _common_pb2.TaskGraph
    def __init__(self, mission_id: _Optional[str] = ..., graph: _Optional[_Union[_common_pb2.TaskGraph, _Mapping]] = ...) -> None: ...

class StartMissionResponse(_message.Message):
    __slots__ = ("mission_id", "graph", "agent_id", "replay_frames", "resumed", "resumed_keyframes")
    MISSION_ID_FIELD_NUMBER: _ClassVar[int]
    GRAPH_FIELD_NUMBER: _ClassVar[int]
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    REPLAY_FRAMES_FIELD_NUMBER: _ClassVar[int]
    RESUMED_FIELD_NUMBER: _ClassVar[int]
    RESUMED_KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    mission_id: str
    graph: _common_pb2.TaskGraph
    agent_id: str
    replay_frames: int
    resumed: bool
    resumed_keyframes: int
    def __init__(self, mission_id: _Optional[str] = ..., graph: _Optional[_Union[_common_pb2.TaskGraph, _Mapping]] = ..., agent_id: _Optional[str] = ..., replay_frames: _Optional[int] = ..., resumed: _Optional[bool] = ..., resumed_keyframes: _Optional[int] = ...) -> None: ...

class FrameMsg(_message.Message):
    __slots__ = ("mission_id", "frame_id", "timestamp", "color", "depth", "depth_scale", "c2w", "intrinsics")
    MISSION_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_FIELD_NUMBER: _ClassVar[int]
    COLOR_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    DEPTH_SCALE_FIELD_NUMBER: _ClassVar[int]
    C2W_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    mission_id: str
    frame_id: int
    timestamp: float
    color: bytes
    depth: bytes
    depth_scale: float
    c2w: _containers.RepeatedScalarFieldContainer[float]
    intrinsics: _common_pb2.Intrinsics
    def __init__(self, mission_id: _Optional[str] = ..., frame_id: _Optional[int] = ..., timestamp: _Optional[float] = ..., color: _Optional[bytes] = ..., depth: _Optional[bytes] = ..., depth_scale: _Optional[float] = ..., c2w: _Optional[_Iterable[float]] = ..., intrinsics: _Optional[_Union[_common_pb2.Intrinsics, _Mapping]] = ...) -> None: ...

class StreamFramesResponse(_message.Message):
    __slots__ = ("mission_id", "frames_received", "frames_mapped")
    MISSION_ID_FIELD_NUMBER: _ClassVar[int]
    FRAMES_RECEIVED_FIELD_NUMBER: _ClassVar[int]
    FRAMES_MAPPED_FIELD_NUMBER: _ClassVar[int]
    mission_id: str
    frames_received: int
    frames_mapped: int
    def __init__(self, mission_id: _Optional[str] = ..., frames_received: _Optional[int] = ..., frames_mapped: _Optional[int] = ...) -> None: ...

class MissionRequest(_message.Message):
    __slots__ = ("mission_id",)
    MISSION_ID_FIELD_NUMBER: _ClassVar[int]
    mission_id: str
    def __init__(self, mission_id: _Optional[str] = ...) -> None: ...

class FinishRequest(_message.Message):
    __slots__ = ("mission_id", "skip_push", "skip_eval")
    MISSION_ID_FIELD_NUMBER: _ClassVar[int]
    SKIP_PUSH_FIELD_NUMBER: _ClassVar[int]
    SKIP_EVAL_FIELD_NUMBER: _ClassVar[int]
    mission_id: str
    skip_push: bool
    skip_eval: bool
    def __init__(self, mission_id: _Optional[str] = ..., skip_push: _Optional[bool] = ..., skip_eval: _Optional[bool] = ...) -> None: ...

class MissionStatus(_message.Message):
    __slots__ = ("mission_id", "agent_id", "state", "task_text", "task_id", "frames_received", "frames_mapped", "frames_queued", "n_gaussians", "n_active", "pushes", "push_failures", "last_pushed_version", "last_error", "seconds_mapping", "keyframes_uploaded", "frames_keyframed", "frames_skipped", "accept_latency_ms_p99", "keyframe_latency_s_p95", "idle_iterations", "checkpoints", "resumed_keyframes", "frames_rejected", "keyframe_iterations", "newest_map_version", "push_backlog", "keyframes_backlog", "link_down_s", "accept_latency_ms_p99_recent", "mapping_width", "mapping_height", "mapping_downscale", "resolution_pinned", "resolution_predicted_iters", "resolution_measured_iters", "resolution_reaches_target", "resolution_changes", "frames_lost", "frames_relocalised", "loop_closures", "keyframe_iters_recent", "roi_iters_recent", "region_width", "region_height", "region_downscale", "region_detail", "region_target_iters", "region_measured_iters", "region_reaches_target", "region_changes", "frames_failed", "corrections_rejected")
    MISSION_ID_FIELD_NUMBER: _ClassVar[int]
    AGENT_ID_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    TASK_TEXT_FIELD_NUMBER: _ClassVar[int]
    TASK_ID_FIELD_NUMBER: _ClassVar[int]
    FRAMES_RECEIVED_FIELD_NUMBER: _ClassVar[int]
    FRAMES_MAPPED_FIELD_NUMBER: _ClassVar[int]
    FRAMES_QUEUED_FIELD_NUMBER: _ClassVar[int]
    N_GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    N_ACTIVE_FIELD_NUMBER: _ClassVar[int]
    PUSHES_FIELD_NUMBER: _ClassVar[int]
    PUSH_FAILURES_FIELD_NUMBER: _ClassVar[int]
    LAST_PUSHED_VERSION_FIELD_NUMBER: _ClassVar[int]
    LAST_ERROR_FIELD_NUMBER: _ClassVar[int]
    SECONDS_MAPPING_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_UPLOADED_FIELD_NUMBER: _ClassVar[int]
    FRAMES_KEYFRAMED_FIELD_NUMBER: _ClassVar[int]
    FRAMES_SKIPPED_FIELD_NUMBER: _ClassVar[int]
    ACCEPT_LATENCY_MS_P99_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_LATENCY_S_P95_FIELD_NUMBER: _ClassVar[int]
    IDLE_ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    CHECKPOINTS_FIELD_NUMBER: _ClassVar[int]
    RESUMED_KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    FRAMES_REJECTED_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    NEWEST_MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    PUSH_BACKLOG_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_BACKLOG_FIELD_NUMBER: _ClassVar[int]
    LINK_DOWN_S_FIELD_NUMBER: _ClassVar[int]
    ACCEPT_LATENCY_MS_P99_RECENT_FIELD_NUMBER: _ClassVar[int]
    MAPPING_WIDTH_FIELD_NUMBER: _ClassVar[int]
    MAPPING_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    MAPPING_DOWNSCALE_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_PINNED_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_PREDICTED_ITERS_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_MEASURED_ITERS_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_REACHES_TARGET_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_CHANGES_FIELD_NUMBER: _ClassVar[int]
    FRAMES_LOST_FIELD_NUMBER: _ClassVar[int]
    FRAMES_RELOCALISED_FIELD_NUMBER: _ClassVar[int]
    LOOP_CLOSURES_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_ITERS_RECENT_FIELD_NUMBER: _ClassVar[int]
    ROI_ITERS_RECENT_FIELD_NUMBER: _ClassVar[int]
    REGION_WIDTH_FIELD_NUMBER: _ClassVar[int]
    REGION_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    REGION_DOWNSCALE_FIELD_NUMBER: _ClassVar[int]
    REGION_DETAIL_FIELD_NUMBER: _ClassVar[int]
    REGION_TARGET_ITERS_FIELD_NUMBER: _ClassVar[int]
    REGION_MEASURED_ITERS_FIELD_NUMBER: _ClassVar[int]
    REGION_REACHES_TARGET_FIELD_NUMBER: _ClassVar[int]
    REGION_CHANGES_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FAILED_FIELD_NUMBER: _ClassVar[int]
    CORRECTIONS_REJECTED_FIELD_NUMBER: _ClassVar[int]
    mission_id: str
    agent_id: str
    state: MissionState
    task_text: str
    task_id: str
    frames_received: int
    frames_mapped: int
    frames_queued: int
    n_gaussians: int
    n_active: int
    pushes: int
    push_failures: int
    last_pushed_version: int
    last_error: str
    seconds_mapping: float
    keyframes_uploaded: int
    frames_keyframed: int
    frames_skipped: int
    accept_latency_ms_p99: float
    keyframe_latency_s_p95: float
    idle_iterations: int
    checkpoints: int
    resumed_keyframes: int
    frames_rejected: int
    keyframe_iterations: int
    newest_map_version: int
    push_backlog: int
    keyframes_backlog: int
    link_down_s: float
    accept_latency_ms_p99_recent: float
    mapping_width: int
    mapping_height: int
    mapping_downscale: float
    resolution_pinned: bool
    resolution_predicted_iters: float
    resolution_measured_iters: float
    resolution_reaches_target: bool
    resolution_changes: int
    frames_lost: int
    frames_relocalised: int
    loop_closures: int
    keyframe_iters_recent: float
    roi_iters_recent: float
    region_width: int
    region_height: int
    region_downscale: float
    region_detail: bool
    region_target_iters: float
    region_measured_iters: float
    region_reaches_target: bool
    region_changes: int
    frames_failed: int
    corrections_rejected: int
    def __init__(self, mission_id: _Optional[str] = ..., agent_id: _Optional[str] = ..., state: _Optional[_Union[MissionState, str]] = ..., task_text: _Optional[str] = ..., task_id: _Optional[str] = ..., frames_received: _Optional[int] = ..., frames_mapped: _Optional[int] = ..., frames_queued: _Optional[int] = ..., n_gaussians: _Optional[int] = ..., n_active: _Optional[int] = ..., pushes: _Optional[int] = ..., push_failures: _Optional[int] = ..., last_pushed_version: _Optional[int] = ..., last_error: _Optional[str] = ..., seconds_mapping: _Optional[float] = ..., keyframes_uploaded: _Optional[int] = ..., frames_keyframed: _Optional[int] = ..., frames_skipped: _Optional[int] = ..., accept_latency_ms_p99: _Optional[float] = ..., keyframe_latency_s_p95: _Optional[float] = ..., idle_iterations: _Optional[int] = ..., checkpoints: _Optional[int] = ..., resumed_keyframes: _Optional[int] = ..., frames_rejected: _Optional[int] = ..., keyframe_iterations: _Optional[int] = ..., newest_map_version: _Optional[int] = ..., push_backlog: _Optional[int] = ..., keyframes_backlog: _Optional[int] = ..., link_down_s: _Optional[float] = ..., accept_latency_ms_p99_recent: _Optional[float] = ..., mapping_width: _Optional[int] = ..., mapping_height: _Optional[int] = ..., mapping_downscale: _Optional[float] = ..., resolution_pinned: _Optional[bool] = ..., resolution_predicted_iters: _Optional[float] = ..., resolution_measured_iters: _Optional[float] = ..., resolution_reaches_target: _Optional[bool] = ..., resolution_changes: _Optional[int] = ..., frames_lost: _Optional[int] = ..., frames_relocalised: _Optional[int] = ..., loop_closures: _Optional[int] = ..., keyframe_iters_recent: _Optional[float] = ..., roi_iters_recent: _Optional[float] = ..., region_width: _Optional[int] = ..., region_height: _Optional[int] = ..., region_downscale: _Optional[float] = ..., region_detail: _Optional[bool] = ..., region_target_iters: _Optional[float] = ..., region_measured_iters: _Optional[float] = ..., region_reaches_target: _Optional[bool] = ..., region_changes: _Optional[int] = ..., frames_failed: _Optional[int] = ..., corrections_rejected: _Optional[int] = ...) -> None: ...

class MissionSummary(_message.Message):
    __slots__ = ("status", "final_push_ok", "n_shared", "share_pct", "bytes_on_wire", "bytes_per_gaussian", "has_roi_psnr", "roi_psnr", "psnr", "seconds_per_frame", "has_roi_psnr_all_frames", "roi_psnr_all_frames", "frames_all", "total_upload_bytes", "final_subset_bytes", "pushes", "protocols", "view_bytes", "views_sent", "views_unsent", "tracked_views", "predicted_views")
    class ProtocolsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: ProtocolScore
        def __init__(self, key: _Optional[str] = ..., value: _Optional[_Union[ProtocolScore, _Mapping]] = ...) -> None: ...
    STATUS_FIELD_NUMBER: _ClassVar[int]
    FINAL_PUSH_OK_FIELD_NUMBER: _ClassVar[int]
    N_SHARED_FIELD_NUMBER: _ClassVar[int]
    SHARE_PCT_FIELD_NUMBER: _ClassVar[int]
    BYTES_ON_WIRE_FIELD_NUMBER: _ClassVar[int]
    BYTES_PER_GAUSSIAN_FIELD_NUMBER: _ClassVar[int]
    HAS_ROI_PSNR_FIELD_NUMBER: _ClassVar[int]
    ROI_PSNR_FIELD_NUMBER: _ClassVar[int]
    PSNR_FIELD_NUMBER: _ClassVar[int]
    SECONDS_PER_FRAME_FIELD_NUMBER: _ClassVar[int]
    HAS_ROI_PSNR_ALL_FRAMES_FIELD_NUMBER: _ClassVar[int]
    ROI_PSNR_ALL_FRAMES_FIELD_NUMBER: _ClassVar[int]
    FRAMES_ALL_FIELD_NUMBER: _ClassVar[int]
    TOTAL_UPLOAD_BYTES_FIELD_NUMBER: _ClassVar[int]
    FINAL_SUBSET_BYTES_FIELD_NUMBER: _ClassVar[int]
    PUSHES_FIELD_NUMBER: _ClassVar[int]
    PROTOCOLS_FIELD_NUMBER: _ClassVar[int]
    VIEW_BYTES_FIELD_NUMBER: _ClassVar[int]
    VIEWS_SENT_FIELD_NUMBER: _ClassVar[int]
    VIEWS_UNSENT_FIELD_NUMBER: _ClassVar[int]
    TRACKED_VIEWS_FIELD_NUMBER: _ClassVar[int]
    PREDICTED_VIEWS_FIELD_NUMBER: _ClassVar[int]
    status: MissionStatus
    final_push_ok: bool
    n_shared: int
    share_pct: float
    bytes_on_wire: int
    bytes_per_gaussian: float
    has_roi_psnr: bool
    roi_psnr: float
    psnr: float
    seconds_per_frame: float
    has_roi_psnr_all_frames: bool
    roi_psnr_all_frames: float
    frames_all: int
    total_upload_bytes: int
    final_subset_bytes: int
    pushes: _containers.RepeatedCompositeFieldContainer[PushInfo]
    protocols: _containers.MessageMap[str, ProtocolScore]
    view_bytes: int
    views_sent: int
    views_unsent: int
    tracked_views: _containers.RepeatedCompositeFieldContainer[TrackedPose]
    predicted_views: _containers.RepeatedCompositeFieldContainer[TrackedPose]
    def __init__(self, status: _Optional[_Union[MissionStatus, _Mapping]] = ..., final_push_ok: _Optional[bool] = ..., n_shared: _Optional[int] = ..., share_pct: _Optional[float] = ..., bytes_on_wire: _Optional[int] = ..., bytes_per_gaussian: _Optional[float] = ..., has_roi_psnr: _Optional[bool] = ..., roi_psnr: _Optional[float] = ..., psnr: _Optional[float] = ..., seconds_per_frame: _Optional[float] = ..., has_roi_psnr_all_frames: _Optional[bool] = ..., roi_psnr_all_frames: _Optional[float] = ..., frames_all: _Optional[int] = ..., total_upload_bytes: _Optional[int] = ..., final_subset_bytes: _Optional[int] = ..., pushes: _Optional[_Iterable[_Union[PushInfo, _Mapping]]] = ..., protocols: _Optional[_Mapping[str, ProtocolScore]] = ..., view_bytes: _Optional[int] = ..., views_sent: _Optional[int] = ..., views_unsent: _Optional[int] = ..., tracked_views: _Optional[_Iterable[_Union[TrackedPose, _Mapping]]] = ..., predicted_views: _Optional[_Iterable[_Union[TrackedPose, _Mapping]]] = ...) -> None: ...

class TrackedPose(_message.Message):
    __slots__ = ("frame_id", "pose", "exposure")
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    EXPOSURE_FIELD_NUMBER: _ClassVar[int]
    frame_id: int
    pose: _common_pb2.Pose
    exposure: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, frame_id: _Optional[int] = ..., pose: _Optional[_Union[_common_pb2.Pose, _Mapping]] = ..., exposure: _Optional[_Iterable[float]] = ...) -> None: ...

class ProtocolScore(_message.Message):
    __slots__ = ("has_roi_psnr", "roi_psnr", "psnr", "ssim", "frames_scored", "roi_frames", "roi_psnr_per_frame")
    class RoiPsnrPerFrameEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: int
        value: float
        def __init__(self, key: _Optional[int] = ..., value: _Optional[float] = ...) -> None: ...
    HAS_ROI_PSNR_FIELD_NUMBER: _ClassVar[int]
    ROI_PSNR_FIELD_NUMBER: _ClassVar[int]
    PSNR_FIELD_NUMBER: _ClassVar[int]
    SSIM_FIELD_NUMBER: _ClassVar[int]
    FRAMES_SCORED_FIELD_NUMBER: _ClassVar[int]
    ROI_FRAMES_FIELD_NUMBER: _ClassVar[int]
    ROI_PSNR_PER_FRAME_FIELD_NUMBER: _ClassVar[int]
    has_roi_psnr: bool
    roi_psnr: float
    psnr: float
    ssim: float
    frames_scored: int
    roi_frames: int
    roi_psnr_per_frame: _containers.ScalarMap[int, float]
    def __init__(self, has_roi_psnr: _Optional[bool] = ..., roi_psnr: _Optional[float] = ..., psnr: _Optional[float] = ..., ssim: _Optional[float] = ..., frames_scored: _Optional[int] = ..., roi_frames: _Optional[int] = ..., roi_psnr_per_frame: _Optional[_Mapping[int, float]] = ...) -> None: ...

class PushInfo(_message.Message):
    __slots__ = ("version", "n_shared", "n_total", "bytes_sent", "delta", "records", "removed", "frames_mapped", "unchanged")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    N_SHARED_FIELD_NUMBER: _ClassVar[int]
    N_TOTAL_FIELD_NUMBER: _ClassVar[int]
    BYTES_SENT_FIELD_NUMBER: _ClassVar[int]
    DELTA_FIELD_NUMBER: _ClassVar[int]
    RECORDS_FIELD_NUMBER: _ClassVar[int]
    REMOVED_FIELD_NUMBER: _ClassVar[int]
    FRAMES_MAPPED_FIELD_NUMBER: _ClassVar[int]
    UNCHANGED_FIELD_NUMBER: _ClassVar[int]
    version: int
    n_shared: int
    n_total: int
    bytes_sent: int
    delta: bool
    records: int
    removed: int
    frames_mapped: int
    unchanged: bool
    def __init__(self, version: _Optional[int] = ..., n_shared: _Optional[int] = ..., n_total: _Optional[int] = ..., bytes_sent: _Optional[int] = ..., delta: _Optional[bool] = ..., records: _Optional[int] = ..., removed: _Optional[int] = ..., frames_mapped: _Optional[int] = ..., unchanged: _Optional[bool] = ...) -> None: ...
