"""Read a sequence in a reader process: decoding stays off the front end's GIL.

Decoding a frame (MCAP chunk decompression, CDR parsing, PNG decoding) is partly pure Python:
about 2 ms per stereo frame, all of it holding the GIL that the front-end thread needs back
after each OpenCV call. :func:`prefetched_messages` runs ``seq.messages()`` in a spawned
process instead, a bounded number of frames ahead.

Transport: the images go through a ring of shared-memory slots, so the main process only copies
them out (one memcpy per image). Sending them through the queue was measured to be no better
than decoding in place: the pipe delivers a 720 KB pickle in 64 KB reads, each taking the GIL
again, and unpickling copies once more. The queue carries a small message per frame: the
frame's time, index, slot and image shapes, and the IMU samples since the previous frame as
one ``ImuBatch``. A frame whose images do not fit a slot travels inline.

The messages, their order and the sequence's warnings are exactly those of ``seq.messages()``;
an error while reading is re-raised here with its own type and message.
"""

from __future__ import annotations

import multiprocessing as mp
import queue
import time
from collections.abc import Iterator
from multiprocessing import shared_memory
from typing import Any

import numpy as np

from datasets.sequence import Sequence
from slam.core.messages import ImuBatch, ImuSample, ReaderBundle, ReaderEnd, StereoFrame
from slam.runtime.priority import apply_role, ignore_stop_signals
from slam.runtime.worker import main_process_gone, name_this_process


def _slot_bytes(seq: Sequence) -> int:
    """Bytes of one stereo frame of 8-bit images at the calibrated size."""
    return sum(c.intrinsics.width * c.intrinsics.height for c in seq.calibration.cameras[:2])


def _pack(
    imu: list[ImuSample], frame: StereoFrame | None, ring: Any, slot: int, slot_bytes: int
) -> ReaderBundle:
    batch = ImuBatch.from_samples(imu)
    if frame is None:
        return ReaderBundle(batch)
    images = [im for im in (frame.left, frame.right) if im is not None]
    fits = sum(im.nbytes for im in images) <= slot_bytes and all(
        im.dtype == np.uint8 for im in images
    )
    if slot < 0 or not fits:
        inline = (frame.left, frame.right)
        return ReaderBundle(batch, frame.t_ns, frame.index, -1, (), inline, frame.exposure_ns)
    offset = slot * slot_bytes
    for im in images:
        np.ndarray(im.shape, np.uint8, ring.buf, offset)[...] = im
        offset += im.nbytes
    shapes = tuple(im.shape for im in images)
    return ReaderBundle(batch, frame.t_ns, frame.index, slot, shapes, (), frame.exposure_ns)


def _reader(
    seq: Sequence, out: Any, free: Any, ring_name: str, slots: int, stop: Any, idle: bool
) -> None:
    """The reader process: bundles, then :class:`ReaderEnd` or the exception.

    It runs at the reader role's priority (``slam.runtime.priority``): it is on the data path,
    so it never runs under SCHED_IDLE (which starved it beside busy processes). Slots are used
    round robin; ``free`` counts the slots the consumer has emptied.
    """
    ignore_stop_signals()
    name_this_process("slam-reader")
    apply_role("reader", idle)

    def wait_for_parent(step: Any) -> Any:
        while True:  # a killed main process never reads again: notice it and end
            try:
                return step()
            except queue.Full:
                if main_process_gone():
                    raise SystemExit(0) from None

    def acquire_slot() -> None:
        while not free.acquire(timeout=1.0):
            if main_process_gone():
                raise SystemExit(0)

    ring = shared_memory.SharedMemory(name=ring_name)
    slot_bytes = ring.size // slots
    try:
        imu: list[ImuSample] = []
        next_slot = 0
        for msg in seq.messages():
            if isinstance(msg, ImuSample):
                imu.append(msg)
                continue
            acquire_slot()
            bundle = _pack(imu, msg, ring, next_slot, slot_bytes)
            if bundle.slot < 0:
                free.release()  # inline: the slot stays free
            else:
                next_slot = (next_slot + 1) % slots
            wait_for_parent(lambda b=bundle: out.put(b, timeout=1.0))
            imu = []
            if stop.is_set():
                return
        if imu:
            wait_for_parent(lambda: out.put(_pack(imu, None, ring, -1, 0), timeout=1.0))
        wait_for_parent(lambda: out.put(ReaderEnd(tuple(seq.warnings)), timeout=1.0))
    except (KeyboardInterrupt, SystemExit):
        return  # Ctrl-C is the main process's to handle; SystemExit: it has died
    except BaseException as exc:  # handed to the consumer, which re-raises it
        out.put(exc)
    finally:
        ring.close()


def _unpack(bundle: ReaderBundle, ring: Any, slot_bytes: int) -> list[ImuSample | StereoFrame]:
    msgs: list[ImuSample | StereoFrame] = list(bundle.imu.samples())
    if bundle.t_ns is None:
        return msgs
    if bundle.slot < 0:
        left, right = bundle.inline
        assert left is not None
    else:
        offset = bundle.slot * slot_bytes
        images = []
        for shape in bundle.shapes:
            im = np.ndarray(shape, np.uint8, ring.buf, offset).copy()
            offset += im.nbytes
            images.append(im)
        left, right = images[0], images[1] if len(images) > 1 else None
    msgs.append(StereoFrame(bundle.t_ns, left, right, bundle.index, exposure_ns=bundle.exposure_ns))
    return msgs


def prefetched_messages(
    seq: Sequence, frames_ahead: int = 8, idle: bool = False
) -> Iterator[ImuSample | StereoFrame]:
    """``seq.messages()``, decoded in a reader process at most ``frames_ahead`` frames ahead
    (``idle``: passed to the reader's priority role, which never idles).

    The reader starts at the first ``next()``; closing the generator (or leaving a ``for`` loop
    over it early) stops it. Warnings the reader collects are appended to ``seq.warnings`` at
    the end of the sequence.
    """
    ctx = mp.get_context("spawn")  # threads may be running: no fork
    slot_bytes = max(_slot_bytes(seq), 1)
    ring = shared_memory.SharedMemory(create=True, size=slot_bytes * frames_ahead)
    free = ctx.Semaphore(frames_ahead)
    out: Any = ctx.Queue(maxsize=frames_ahead + 1)
    stop = ctx.Event()
    proc = ctx.Process(
        target=_reader,
        args=(seq, out, free, ring.name, frames_ahead, stop, idle),
        daemon=True,
        name="slam-reader",
    )
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
            if isinstance(item, ReaderEnd):
                seq.warnings.extend(w for w in item.warnings if w not in seq.warnings)
                return
            msgs = _unpack(item, ring, slot_bytes)
            if item.slot >= 0:
                free.release()  # copied out: the reader may fill the slot again
            yield from msgs
    finally:
        stop.set()
        deadline = time.monotonic() + 5.0
        while proc.is_alive() and time.monotonic() < deadline:
            try:  # unblock a reader waiting on a full queue or a slot; it then sees ``stop``
                item = out.get(timeout=0.1)
                if isinstance(item, ReaderBundle) and item.slot >= 0:
                    free.release()
            except queue.Empty:
                proc.join(timeout=0.1)
        if proc.is_alive():
            proc.terminate()
        proc.join(timeout=1.0)
        out.close()
        out.cancel_join_thread()
        ring.close()
        ring.unlink()
