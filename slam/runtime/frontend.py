"""The front end as a pipeline stage: every frame in; tracking results, keyframes and the front
end's corrections out."""

from __future__ import annotations

from typing import Any

import cv2

from slam.core.messages import StereoFrame
from slam.frontend.tracker import FrontEnd
from slam.runtime.stage import Stage


class FrontendStage(Stage):
    """Runs the front end on each frame and emits what it made, in this order: the
    :class:`FrontendCorrection`\\ s it applied, the :class:`TrackingResult`, the
    :class:`Keyframe` if it made one."""

    def __init__(self, frontend: FrontEnd, threaded: bool, queue_size: int):
        super().__init__("frontend", maxsize=queue_size, threaded=threaded)
        self.frontend = frontend
        threads = frontend.cfg.opencv_threads
        cv2.setNumThreads(threads if threads > 0 else -1)  # this process's OpenCV; -1: default

    def process(self, msg: Any) -> None:
        assert isinstance(msg, StereoFrame)
        result = self.frontend.track(msg)
        for correction in self.frontend.take_corrections():
            self.emit(correction)
        self.emit(result)  # the pose goes out before the keyframe work (FrontEnd.after_pose)
        keyframe = self.frontend.after_pose()
        if keyframe is not None:
            self.emit(keyframe)

    def finish_frontend(self) -> None:
        """After the back end has ended: a change of frame it published after the last frame
        (:meth:`FrontEnd.finish`) still reaches the recorder and the loop closer."""
        self.frontend.finish()
        for correction in self.frontend.take_corrections():
            self.emit(correction)
