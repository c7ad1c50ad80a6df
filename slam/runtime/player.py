"""The player: reads the sequence and hands it to the pipeline at sensor rate, faster, or as
fast as the front end takes it; counts what it drops; shows progress; stops when told.

IMU samples go to the front end's buffer and to the IMU consumers as one :class:`ImuBatch` per
frame. In real-time playback (``speed`` > 0, concurrent) a frame the front end has no room for
is dropped and counted; otherwise the player waits for it.
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from typing import Any

from slam.core.messages import ImuBatch, ImuSample, StereoFrame
from slam.imu_buffer import ImuBuffer
from slam.runtime.control import RunControl
from slam.runtime.stage import Stage, StageError


@dataclass
class PlayState:
    """What the player has done so far (read by the stats while it runs)."""

    frames_in: int = 0
    frames_dropped: int = 0
    t_first_ns: int | None = None
    t_last_ns: int = 0
    error: StageError | None = None

    @property
    def sequence_s(self) -> float:
        return 0.0 if self.t_first_ns is None else (self.t_last_ns - self.t_first_ns) * 1e-9


def at_mid_exposure(
    messages: Iterator[ImuSample | StereoFrame],
) -> Iterator[ImuSample | StereoFrame]:
    """``messages`` with every frame of known exposure stamped at the middle of it
    (:func:`slam.core.messages.mid_exposure_ns`: the time its image shows; a driver stamps
    the end of the exposure). Everything downstream (the front end's IMU prediction, the back end's
    preintegration and time offset, the outputs) then uses that time. Auto-exposure moves the
    middle by milliseconds from frame to frame, which no constant time offset follows.
    Frames of unknown exposure (0) keep their stamp; stamps stay increasing."""
    last_ns = -(2**62)
    try:
        for msg in messages:
            if isinstance(msg, StereoFrame) and msg.exposure_ns > 0:
                t_ns = max(msg.mid_exposure_ns, last_ns + 1)
                msg = dataclasses.replace(msg, t_ns=t_ns)
            if isinstance(msg, StereoFrame):
                last_ns = msg.t_ns
            yield msg
    finally:
        if isinstance(messages, Generator):
            messages.close()


def restamped(
    messages: Iterator[ImuSample | StereoFrame], offset_ns: Callable[[], int]
) -> Iterator[ImuSample | StereoFrame]:
    """``messages`` with every frame stamped in the IMU's clock: its stamp plus the camera-IMU
    offset the back end estimates online (``offset_ns()``, read when the frame arrives; it says
    which it carries, ``StereoFrame.time_offset_ns``). A frame whose new stamp is ahead of the
    IMU waits for the samples up to it, so every stage still sees the IMU up to each frame.
    Stamps stay increasing."""
    held: deque[StereoFrame] = deque()
    last_ns = -(2**62)
    try:
        for msg in messages:
            if isinstance(msg, ImuSample):
                while held and held[0].t_ns <= msg.t_ns:
                    yield held.popleft()
                yield msg
                continue
            d = int(offset_ns())
            t_ns = max(msg.t_ns + d, last_ns + 1)
            last_ns = t_ns
            frame = dataclasses.replace(msg, t_ns=t_ns, time_offset_ns=t_ns - msg.t_ns)
            if held or d > 0:
                held.append(frame)
            else:
                yield frame
        yield from held
    finally:
        if isinstance(messages, Generator):
            messages.close()


def real_time_factor(sequence_s: float, wall_s: float) -> float:
    """Sequence time processed per wall-clock second (the one formula, in the progress bar
    and the summary)."""
    return sequence_s / wall_s if wall_s > 0 else 0.0


def play(
    messages: Iterator[ImuSample | StereoFrame],
    frontend: Stage,
    imu_buffer: ImuBuffer | None,
    imu_consumers: list[Stage],
    stages: list[Stage],
    state: PlayState,
    control: RunControl,
    *,
    speed: float,
    sequential: bool,
    max_frames: int,
    t_wall0: float,
    bar: Any = None,
    last_state: Callable[[], str] = lambda: "",
    every_few_seconds: Callable[[], None] = lambda: None,
    flush_every_s: float = 5.0,
) -> None:
    """Play ``messages`` into ``frontend`` until the end, ``max_frames``, a stage error or a
    stop request."""
    imu_pending: list[ImuSample] = []

    def flush_imu() -> None:
        if not imu_pending:
            return
        batch = ImuBatch.from_samples(imu_pending)
        if imu_buffer is not None:
            imu_buffer.extend_batch(batch)
        for consumer in imu_consumers:
            consumer.put(batch)
        imu_pending.clear()

    last_flush = time.perf_counter()
    try:
        for msg in messages:
            if control.stop.is_set():
                break
            if state.t_first_ns is None:
                state.t_first_ns = msg.t_ns
            if isinstance(msg, ImuSample):
                imu_pending.append(msg)  # handed on with the next frame, in one message
                continue
            if speed > 0:  # paced per frame (IMU samples wait for their frame anyway)
                ahead = (msg.t_ns - state.t_first_ns) * 1e-9 / speed - (
                    time.perf_counter() - t_wall0
                )
                if ahead > 0 and control.stop.wait(ahead):
                    break
            flush_imu()
            if max_frames and state.frames_in >= max_frames:
                break
            state.frames_in += 1
            state.t_last_ns = msg.t_ns
            if not frontend.put(msg, block=sequential or speed <= 0):
                state.frames_dropped += 1
            failed = next((s.error for s in stages if s.error is not None), None)
            if failed is not None:
                state.error = failed
                break
            if bar is not None:
                bar.update(1)
                if state.frames_in % 10 == 0:
                    rtf = real_time_factor(state.sequence_s, time.perf_counter() - t_wall0)
                    bar.set_postfix(
                        rtf=f"{rtf:.2f}",
                        state=last_state(),
                        dropped=state.frames_dropped,
                        refresh=False,
                    )
            now = time.perf_counter()
            if now - last_flush > flush_every_s:
                every_few_seconds()
                last_flush = now
    finally:
        if isinstance(messages, Generator):
            messages.close()  # stops the reader process when the loop ended early
