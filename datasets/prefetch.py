"""Read a sequence in a reader process: decoding stays off the front end's GIL.

Decoding a frame (MCAP chunk decompression, CDR parsing, PNG decoding) is partly pure Python:
about 2 ms per stereo frame, all of it holding the GIL that the front-end thread needs back
after each OpenCV call. :func:`prefetched_messages` runs ``seq.messages()`` in a spawned
process instead and hands the messages over in one bundle per frame (the IMU samples since the
previous frame, then the frame), a bounded number of frames ahead. The main process only
unpickles (a copy of the image bytes).

The messages, their order and the sequence's warnings are exactly those of ``seq.messages()``;
an error while reading is re-raised here with its own type and message.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import time
from collections.abc import Iterator
from typing import Any

from datasets.sequence import Sequence
from slam.messages import ImuSample, StereoFrame

_END = "end"
READER_NICE = 5


def _reader(seq: Sequence, out: Any, stop: Any) -> None:
    """The reader process: bundles of messages, then ``(_END, warnings)`` or the exception.

    It runs niced: it only has to stay a few frames ahead, the front end must answer each one.
    """
    try:
        os.nice(READER_NICE)
    except OSError:
        pass
    try:
        bundle: list[ImuSample | StereoFrame] = []
        for msg in seq.messages():
            bundle.append(msg)
            if isinstance(msg, StereoFrame):
                out.put(bundle)
                bundle = []
                if stop.is_set():
                    return
        if bundle:
            out.put(bundle)
        out.put((_END, list(seq.warnings)))
    except KeyboardInterrupt:
        return  # the main process handles Ctrl-C
    except BaseException as exc:  # handed to the consumer, which re-raises it
        out.put(exc)


def prefetched_messages(seq: Sequence, frames_ahead: int = 8) -> Iterator[ImuSample | StereoFrame]:
    """``seq.messages()``, decoded in a reader process at most ``frames_ahead`` frames ahead.

    The reader starts at the first ``next()``; closing the generator (or leaving a ``for`` loop
    over it early) stops it. Warnings the reader collects are appended to ``seq.warnings`` at
    the end of the sequence.
    """
    ctx = mp.get_context("spawn")  # threads may be running: no fork
    out: Any = ctx.Queue(maxsize=frames_ahead)
    stop = ctx.Event()
    proc = ctx.Process(target=_reader, args=(seq, out, stop), daemon=True, name="slam-reader")
    proc.start()
    try:
        while True:
            try:
                item = out.get(timeout=1.0)
            except queue.Empty:
                if not proc.is_alive():
                    raise RuntimeError(
                        f"the reader process of {seq.name} died (exit code {proc.exitcode})"
                    ) from None
                continue
            if isinstance(item, BaseException):
                raise item
            if isinstance(item, tuple) and item[0] == _END:
                seq.warnings.extend(w for w in item[1] if w not in seq.warnings)
                return
            yield from item
    finally:
        stop.set()
        deadline = time.monotonic() + 5.0
        while proc.is_alive() and time.monotonic() < deadline:
            try:  # unblock a reader waiting on a full queue; it then sees ``stop``
                out.get(timeout=0.1)
            except queue.Empty:
                proc.join(timeout=0.1)
        if proc.is_alive():
            proc.terminate()
        proc.join(timeout=1.0)
        out.close()
        out.cancel_join_thread()
