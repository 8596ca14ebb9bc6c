"""The keyframes and refinement views a mission sends the fusion server (``agent.upload_keyframe_every``,
``agent.refine_views``; docs/sharing.md): a fusion session keeps one image size, the one of the mapping resolution
chosen at the first keyframe, so a keyframe mapped at another resolution later is sent at that first size.
"""

from __future__ import annotations

from typing import Callable, Iterator, Optional

import numpy as np

from gausslite.datasets.base import Frame
from gausslite.mission.config import AgentConfig

__all__ = ["KeyframeUploads"]


class KeyframeUploads:
    """The image size of a mission's uploads and the views it sends.

    Args:
        config: the mission's ``AgentConfig`` (``refine_views.between_every``).
        resolution: the mission's resolution governor (:class:`gausslite.mapping.resolution.ResolutionGovernor`;
            ``factor``: the current mapping downscale).
        intrinsics: ``() -> Intrinsics | None``: the intrinsics of the mission's frames at their native size (None
            before the first frame).

    Attributes:
        factor: the downscale of the uploads, fixed at the first keyframe (:meth:`fix`); None before it.
    """

    def __init__(self, config: AgentConfig, resolution, intrinsics: Callable[[], Optional[object]]) -> None:
        self.config, self.resolution, self._native_intrinsics = config, resolution, intrinsics
        self.factor: Optional[float] = None

    def fix(self) -> None:
        """Fix the uploads' size at the mapping resolution chosen now (the first keyframe's)."""
        self.factor = self.resolution.factor

    @property
    def intrinsics(self):
        """Intrinsics of the keyframes sent to the fusion server: the first frame's at the uploads' downscale (the
        current mapping downscale before :meth:`fix`); None before the first frame."""
        intr = self._native_intrinsics()
        if intr is None:
            return None
        f = self.factor or self.resolution.factor
        return intr if f == 1 else intr.scaled(f)

    @property
    def at_mapping_size(self) -> bool:
        """The mapping resolution is the uploads' (or none is fixed yet): mapped frames go out as they are."""
        return self.factor is None or self.factor == self.resolution.factor

    def keyframe(self, native: Frame, mapped: Frame, relevance: np.ndarray) -> tuple:
        """The keyframe and its relevance map to upload: ``(mapped, relevance)`` at the uploads' size, otherwise
        ``native`` downscaled to it with ``relevance`` (an (H, W) bool mask) resized by nearest neighbour."""
        if self.at_mapping_size:
            return mapped, relevance
        # lazy: keeps gausslite.mission importable without OpenCV
        import cv2

        from gausslite.datasets.common import downscale_frame

        up = downscale_frame(native, self.factor)
        wu = cv2.resize(np.asarray(relevance, np.uint8), (up.intrinsics.width, up.intrinsics.height),
                        interpolation=cv2.INTER_NEAREST) > 0
        return up, wu

    def between_views(self, keyframe: Frame, relevance: np.ndarray, frames: list) -> Iterator[tuple]:
        """The refinement views ``(frame, roi)`` of every ``refine_views.between_every``-th of ``frames`` (the frames
        between the previous keyframe and ``keyframe``, at the mapping resolution; those not decoded are skipped):
        the keyframe's ROI ``relevance`` ((H, W) bool) carried over by depth
        (:func:`gausslite.fusion.views.region_points`, :func:`gausslite.mapping.roi_views.project_roi`). None while
        the mapping resolution differs from the uploads' (the fusion session keeps one image size), nor when the
        keyframe's ROI holds no depth."""
        if not self.at_mapping_size:
            return
        # lazy: keeps gausslite.mission importable without OpenCV
        from gausslite.fusion.views import region_points
        from gausslite.mapping.roi_views import project_roi

        pts = region_points(keyframe, np.asarray(relevance) > 0)
        if len(pts) == 0:
            return
        for fr in frames[::self.config.refine_views.between_every]:
            if isinstance(fr, Frame):
                yield fr, project_roi(pts, np.asarray(fr.depth, np.float32), fr.intrinsics.K, fr.c2w)
