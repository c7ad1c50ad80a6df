"""The front end as a pipeline stage: every frame in; tracking results, keyframes and the front
end's corrections out."""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import Any

import cv2
import numpy as np

from slam.core.errors import SlamError
from slam.core.geometry import rotation_angle_rad
from slam.core.messages import LoopCorrection, StereoFrame, TrackingResult
from slam.frontend.tracker import FrontEnd
from slam.runtime.stage import Stage

_IDENTITY = np.eye(4)
LIVE_CORRECTIONS = ("unanchored", "latest")  # loop.live_correction


class FrontendStage(Stage):
    """Runs the front end on each frame and emits what it made, in this order: the
    :class:`FrontendCorrection`\\ s it applied, the :class:`TrackingResult`, the
    :class:`Keyframe` if it made one."""

    def __init__(
        self,
        frontend: FrontEnd,
        threaded: bool,
        queue_size: int,
        map_source: Callable[[], LoopCorrection | None] | None = None,
        live_correction: str = "unanchored",
    ):
        """``map_source``: the latest loop correction (read without waiting), which puts
        every published pose into the loop-corrected map as well."""
        super().__init__("frontend", maxsize=queue_size, threaded=threaded)
        self.frontend = frontend
        self.map_source = map_source
        if live_correction not in LIVE_CORRECTIONS:
            raise SlamError(
                f"loop.live_correction must be one of {LIVE_CORRECTIONS}, got {live_correction!r}"
            )
        self.live_correction = live_correction
        self._map_generation = 0
        self._correction: LoopCorrection | None = None
        self._applied: tuple[int, np.ndarray] | None = None  # segment, correction last applied
        self.quiet: Callable[[], AbstractContextManager[Any]] = contextlib.nullcontext
        """The context each frame's work runs in (wiring: the mapper's
        :meth:`~slam.runtime.mapper.MapperStage.paused_while_working`, ``mapping.pause_while_tracking``)."""
        threads = frontend.cfg.opencv_threads
        cv2.setNumThreads(threads if threads > 0 else -1)  # this process's OpenCV; -1: default

    def process(self, msg: Any) -> None:
        assert isinstance(msg, StereoFrame)
        with self.quiet():
            result = self._in_map(self.frontend.track(msg))
            for correction in self.frontend.take_corrections():
                self.emit(correction)
            self.emit(result)  # the pose goes out before the keyframe work (FrontEnd.after_pose)
            keyframe = self.frontend.after_pose()
        if keyframe is not None:
            self.emit(keyframe)

    def _in_map(self, result: TrackingResult) -> TrackingResult:
        """The result with its pose in the loop-corrected map as known now: the odometry
        composed with the latest correction of its segment (VINS-Fusion publishes the same;
        loop closure never moves the odometry itself). A frame tracked on old landmarks found
        again in the map (``anchor_keyframe_id``) is already tied to the map: by default
        (``loop.live_correction: unanchored``) its odometry is published as it is; ``latest``
        corrects it too (measured: BENCHMARKS.md, "Precise loop edges"; the correction of the
        keyframe its old landmarks were born at was worse). A change of the correction
        applied is a jump, measured on this frame."""
        corr = None if self.map_source is None else self.map_source()
        if corr is not None and corr.map_generation != self._map_generation:
            self._correction = corr
            self._map_generation = corr.map_generation
        pose = result.world_from_body
        if pose is None:
            return dataclasses.replace(result, map_generation=self._map_generation)
        m = _IDENTITY
        corr = self._correction
        if corr is not None and (result.anchor_keyframe_id < 0 or self.live_correction == "latest"):
            m = corr.map_from_odom.get(result.segment_id, _IDENTITY)
        jump = (0.0, 0.0)
        if self._applied is not None and self._applied[0] == result.segment_id:
            if m is not self._applied[1]:
                jump = _jump(self._applied[1] @ pose, m @ pose)
        self._applied = (result.segment_id, m)
        return dataclasses.replace(
            result,
            map_from_body=m @ pose,
            map_generation=self._map_generation,
            map_jump_m=jump[0],
            map_jump_deg=jump[1],
        )

    def finish_frontend(self) -> None:
        """After the back end has ended: a change of frame it published after the last frame
        (:meth:`FrontEnd.finish`) still reaches the recorder and the loop closer."""
        self.frontend.finish()
        for correction in self.frontend.take_corrections():
            self.emit(correction)


def _jump(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """How far a pose moved: metres, degrees."""
    delta = np.linalg.inv(before) @ after
    return (
        float(np.linalg.norm(after[:3, 3] - before[:3, 3])),
        float(np.degrees(rotation_angle_rad(delta[:3, :3]))),
    )
