"""ROS 2 bags recorded as MCAP (by ``ros2 bag record`` or by us) read as a :class:`Sequence`.

Topics are chosen by the caller (defaults: ours, ``/cam0/image_raw``, ``/cam1/image_raw``,
``/imu0``, ``/groundtruth/pose``). Images may be ``sensor_msgs/msg/Image`` (mono8, bgr8, rgb8,
bgra8, rgba8; converted to grey) or ``sensor_msgs/msg/CompressedImage`` (jpeg/png). Ground truth
may be PoseStamped, PoseWithCovarianceStamped, Odometry or TransformStamped (read as
world_from_body). Timestamps are the messages' header stamps (log time when a stamp is zero);
camera stamps are moved to the IMU clock with ``calibration.time_offset_ns``.

Calibration comes from the caller (e.g. Kalibr files, :mod:`datasets.kalibr`) or from our own
metadata record ``pyvislam.calibration``; without either, opening fails with an error that says
how to pass one.

Opening does one pass over the file (:func:`datasets.mcap_scan.scan_mcap`): IMU and poses are
decoded, images are only located. ``iter_frames`` then streams the images chunk by chunk.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from datasets import cdr
from datasets.mcap_scan import ChunkCache, CorruptChunk, ScanResult, scan_mcap
from datasets.sequence import ImuArrays, Sequence
from datasets.timing import find_gaps, pair_stereo, sort_dedupe
from slam.core.calibration import Calibration
from slam.core.errors import InputError
from slam.core.messages import StereoFrame
from slam.core.trajectory import Trajectory

CALIBRATION_METADATA = "pyvislam.calibration"
SEQUENCE_METADATA = "pyvislam.sequence"

DEFAULT_LEFT_TOPIC = "/cam0/image_raw"
DEFAULT_RIGHT_TOPIC = "/cam1/image_raw"
DEFAULT_IMU_TOPIC = "/imu0"
DEFAULT_GT_TOPIC = "/groundtruth/pose"
DEFAULT_EXPOSURE_TOPIC = "/cam0/exposure"

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
IMU_TYPE = "sensor_msgs/msg/Imu"
EXPOSURE_TYPE = "sensor_msgs/msg/TimeReference"
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/TransformStamped",
)
NO_CALIBRATION_HINT = (
    "pass a Kalibr calibration: --camchain camchain.yaml --imu-yaml imu.yaml "
    "(open_sequence(..., camchain=, imu_yaml=))"
)


@dataclass(frozen=True)
class TopicSelection:
    """Which topics hold what. ``None`` right/imu/gt/exposure topics mean: not used.
    ``exposure``: the left camera's exposure per image (``sensor_msgs/msg/TimeReference`` as
    :func:`datasets.cdr.encode_exposure` writes it), read when present, else unknown."""

    left: str = DEFAULT_LEFT_TOPIC
    right: str | None = DEFAULT_RIGHT_TOPIC
    imu: str | None = DEFAULT_IMU_TOPIC
    gt: str | None = DEFAULT_GT_TOPIC
    exposure: str | None = DEFAULT_EXPOSURE_TOPIC


def embedded_calibration(scan: ScanResult) -> Calibration | None:
    """The calibration our writer stores as a metadata record, or None."""
    record = scan.metadata.get(CALIBRATION_METADATA)
    if not record or "json" not in record:
        return None
    try:
        return Calibration.from_dict(json.loads(record["json"]))
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(
            f"{scan.path}: metadata record {CALIBRATION_METADATA!r} is unreadable ({exc}); "
            + NO_CALIBRATION_HINT
        ) from exc


class Ros2McapSequence(Sequence):
    """A camera(+IMU) sequence inside an MCAP file with ROS 2 cdr messages."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        topics: TopicSelection | None = None,
        calibration: Calibration | None = None,
        required: tuple[str, ...] = (),
        pair_tolerance_ns: int = 2_000_000,
        scan: ScanResult | None = None,
        strict: bool = False,
    ) -> None:
        """Open and index ``path``.

        ``required`` lists which of ``("right", "imu", "gt")`` must exist (topics the user named
        explicitly); others are silently unused when absent (the left camera is always required).
        ``strict``: refuse a truncated file or a corrupt chunk (InputError) instead of keeping
        what can be read with a warning.
        """
        self.path = os.fspath(path)
        if not os.path.isfile(self.path):
            raise InputError(f"{self.path}: no such file")
        topics = topics or TopicSelection()
        self.topics = topics
        self.strict = strict
        self._corrupt_chunks: list[int] | None = None  # set by verify()
        self.scan = scan if scan is not None else scan_mcap(self.path)
        s = self.scan
        seq_meta = s.metadata.get(SEQUENCE_METADATA, {})
        name = seq_meta.get("name") or os.path.splitext(os.path.basename(self.path))[0]
        warnings = list(s.warnings)

        present = s.topics()

        def need(role: str, topic: str | None, allowed: tuple[str, ...]) -> str | None:
            if topic is None:
                return None
            if topic not in present:
                if role == "left" or role in required:
                    raise InputError(
                        f"{self.path}: topic {topic} not found; topics present: "
                        f"{s.describe_topics()} (choose with --left-topic/--right-topic/"
                        "--imu-topic/--gt-topic)"
                    )
                return None
            schema = present[topic][0]
            if schema not in allowed:
                raise InputError(
                    f"{self.path}: topic {topic} has type {schema}, expected "
                    f"{' or '.join(allowed)}; topics present: {s.describe_topics()}"
                )
            for cid in s.channel_ids(topic):
                enc = s.channels[cid].message_encoding
                if enc != "cdr":
                    raise InputError(
                        f"{self.path}: topic {topic} is encoded as {enc!r}; only ROS 2 'cdr' "
                        "messages are supported"
                    )
            return topic

        left = need("left", topics.left, IMAGE_TYPES)
        right = need("right", topics.right, IMAGE_TYPES)
        imu_topic = need("imu", topics.imu, (IMU_TYPE,))
        gt_topic = need("gt", topics.gt, POSE_TYPES)
        assert left is not None
        truncated = s.truncation_note(left, "frames")
        if truncated:
            warnings.append(truncated)
        elif s.skipped_chunks and s.recorded is not None and left in s.recorded.counts:
            total = s.recorded.counts[left]
            lost = total - int(s.topic_mask(left).sum())
            if lost > 0:
                warnings.append(
                    f"{lost} of {total} frames were in the corrupt chunk(s) and are lost "
                    f"(totals from {s.recorded.source})"
                )
        if strict and (s.lost_data or s.skipped_chunks):
            first = truncated if s.lost_data else None
            first = first or next(w for w in s.warnings if w.startswith("corrupt chunk"))
            raise InputError(f"{self.path}: {first}; run without --strict to use what can be read")

        if calibration is None:
            calibration = embedded_calibration(s)
        if calibration is None:
            raise InputError(f"{self.path} carries no calibration; " + NO_CALIBRATION_HINT)
        if right is not None and not calibration.is_stereo:
            warnings.append(f"calibration has one camera: {right} is ignored (mono)")
            right = None
        offset_ns = int(calibration.time_offset_ns)

        # --- cameras ---------------------------------------------------------------------------
        left_msgs, left_t = self._topic_times(left, warnings, offset_ns)
        self._left_decode = self._decoder(left)
        self._check_first_image(left, left_msgs)
        if right is not None:
            right_msgs, right_t = self._topic_times(right, warnings, offset_ns)
            self._check_first_image(right, right_msgs)
            self._right_decode = self._decoder(right)
            pairing = pair_stereo(left_t, right_t, pair_tolerance_ns)
            if pairing.unmatched_left or pairing.unmatched_right:
                warnings.append(
                    f"stereo pairing (tolerance {pair_tolerance_ns * 1e-6:g} ms): "
                    f"{pairing.unmatched_left} left and {pairing.unmatched_right} right frames "
                    "had no partner and were dropped"
                )
            self._left_msg = left_msgs[pairing.left]
            self._right_msg: np.ndarray | None = right_msgs[pairing.right]
            frame_t = left_t[pairing.left]
        else:
            self._left_msg = left_msgs
            self._right_msg = None
            frame_t = left_t
        self._frame_t_ns = frame_t + offset_ns
        self._exposure_ns = self._read_exposure(topics.exposure, frame_t, warnings)
        if len(self._frame_t_ns) == 0:
            raise InputError(f"{self.path}: no readable camera frames on {left}")

        # --- IMU -------------------------------------------------------------------------------
        self._imu = self._read_imu(imu_topic, warnings)
        # --- ground truth ----------------------------------------------------------------------
        ground_truth = self._read_gt(gt_topic, warnings) if gt_topic else None

        super().__init__(name=name, calibration=calibration, ground_truth=ground_truth)
        for w in warnings:
            self.warn(w)
        self._cache = ChunkCache(s, max_chunks=3)
        if strict:  # CRC-check the lazily indexed chunks now: refuse before a run, not in it
            before = len(self.warnings)
            if self.verify():
                raise InputError(
                    f"{self.path}: {self.warnings[before]}; run without --strict to skip the "
                    "frames of corrupt chunks"
                )

    # --- indexing helpers ----------------------------------------------------------------------
    def _topic_times(
        self, topic: str, warnings: list[str], offset_ns: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Message numbers of a topic and their header stamps, cleaned (sorted, no repeats).

        Images of lazily indexed chunks (our writer's layout) have no head read yet: our writer
        stamps them ``log time - offset``, so that is their stamp.
        """
        s = self.scan
        msgs = np.nonzero(np.isin(s.msg_channel, s.channel_ids(topic)))[0]
        stamps = np.array(
            [
                cdr.stamp_ns(s.heads[i]) if s.msg_length[i] >= 0 else s.msg_log_ns[i] - offset_ns
                for i in msgs
            ],
            dtype=np.int64,
        )
        zero = (stamps == 0) & (s.msg_log_ns[msgs] != 0)  # a zero stamp at log time 0 is real
        if np.any(zero):
            stamps[zero] = s.msg_log_ns[msgs[zero]]
            warnings.append(
                f"{topic}: {int(zero.sum())} messages without a header stamp (log time used)"
            )
        cleaned = sort_dedupe(stamps)
        note = cleaned.describe(topic)
        if note:
            warnings.append(note)
        return msgs[cleaned.keep], stamps[cleaned.keep]

    def _decoder(self, topic: str):  # type: ignore[no-untyped-def]
        if self.scan.schema_name(topic) == "sensor_msgs/msg/CompressedImage":
            return cdr.decode_compressed_image_grey
        return cdr.decode_image_grey

    def _check_first_image(self, topic: str, msgs: np.ndarray) -> None:
        if len(msgs) == 0 or self.scan.schema_name(topic) != "sensor_msgs/msg/Image":
            return
        head = self.scan.heads[int(msgs[0])]
        if not head:  # lazily indexed (our writer: mono8); decoding checks it anyway
            return
        try:
            enc = cdr.parse_image_header(head).encoding
        except Exception:  # noqa: BLE001 - head may cut a huge frame_id; decode will tell
            return
        if enc.lower() not in cdr.GREY_ENCODINGS:
            raise InputError(
                f"{self.path}: topic {topic} has image encoding {enc!r}, not one of "
                f"{', '.join(sorted(cdr.GREY_ENCODINGS))}; topics present: "
                f"{self.scan.describe_topics()}"
            )

    def _read_imu(self, topic: str | None, warnings: list[str]) -> ImuArrays:
        if topic is None:
            return ImuArrays(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
        s = self.scan
        msgs = np.nonzero(np.isin(s.msg_channel, s.channel_ids(topic)))[0]
        t, gyro, accel = cdr.decode_imu_many([s.heads[i] for i in msgs])
        zero = (t == 0) & (s.msg_log_ns[msgs] != 0)
        t[zero] = s.msg_log_ns[msgs[zero]]
        vals = np.concatenate([gyro, accel], axis=1)
        cleaned = sort_dedupe(t)
        note = cleaned.describe(topic)
        if note:
            warnings.append(note)
        t, vals = t[cleaned.keep], vals[cleaned.keep]
        gap_note = find_gaps(t).describe(topic)
        if gap_note:
            warnings.append(gap_note)
        return ImuArrays(t, np.ascontiguousarray(vals[:, :3]), np.ascontiguousarray(vals[:, 3:]))

    def _read_exposure(
        self, topic: str | None, frame_t: np.ndarray, warnings: list[str]
    ) -> np.ndarray | None:
        """Each frame's exposure (ns; 0 where no message has its stamp), from ``topic`` (see
        :class:`TopicSelection`), or None when the file has no such topic. ``frame_t``: the
        frames' camera stamps. A topic of another type or form is warned about and unused."""
        s = self.scan
        present = s.topics()
        if topic is None or topic not in present:
            return None
        if present[topic][0] != EXPOSURE_TYPE:
            warnings.append(
                f"{topic} has type {present[topic][0]}, not {EXPOSURE_TYPE}: exposure unknown"
            )
            return None
        msgs = np.nonzero(np.isin(s.msg_channel, s.channel_ids(topic)))[0]
        try:
            pairs = np.array([cdr.decode_exposure(s.heads[i]) for i in msgs], np.int64)
        except (InputError, struct.error) as exc:
            warnings.append(f"{topic}: unreadable ({exc}): exposure unknown")
            return None
        exposure = np.zeros(len(frame_t), np.int64)
        if len(pairs):
            pairs = pairs[np.argsort(pairs[:, 0], kind="stable")]
            stamps, durations = pairs[:, 0], pairs[:, 1]
            at = np.clip(np.searchsorted(stamps, frame_t), 0, len(stamps) - 1)
            found = stamps[at] == frame_t
            exposure[found] = durations[at[found]]
            missing = int(len(frame_t) - found.sum())
            if missing:
                warnings.append(f"{topic}: {missing} frames have no exposure (taken as unknown)")
        return exposure

    def _read_gt(self, topic: str, warnings: list[str]) -> Trajectory | None:
        s = self.scan
        msgs = np.nonzero(np.isin(s.msg_channel, s.channel_ids(topic)))[0]
        if len(msgs) == 0:
            return None
        schema = s.schema_name(topic)
        t = np.empty(len(msgs), np.int64)
        pos = np.empty((len(msgs), 3))
        q = np.empty((len(msgs), 4))
        if schema == "geometry_msgs/msg/PoseStamped":
            for k, i in enumerate(msgs):
                t[k], pos[k], q[k] = cdr.decode_pose_stamped(s.heads[i])
        else:
            cache = ChunkCache(s, max_chunks=2)
            for k, i in enumerate(msgs):
                t[k], pos[k], q[k] = _decode_pose_generic(bytes(cache.payload(int(i))), schema)
            cache.close()
        cleaned = sort_dedupe(t)
        note = cleaned.describe(topic)
        if note:
            warnings.append(note)
        keep = cleaned.keep
        qk = q[keep]
        norm = np.linalg.norm(qk, axis=1, keepdims=True)
        if np.any(np.abs(norm - 1.0) > 1e-9):  # keep exact values when already unit
            qk = qk / norm
        return Trajectory(t_ns=t[keep], positions_m=pos[keep], q_wxyz=qk)

    # --- Sequence API --------------------------------------------------------------------------
    def frame_times_ns(self) -> np.ndarray:
        return self._frame_t_ns

    def imu(self) -> ImuArrays:
        return self._imu

    def exposures_ns(self) -> np.ndarray | None:
        return self._exposure_ns

    def _decode(self, cache: ChunkCache, index: int) -> StereoFrame:
        left = self._left_decode(cache.payload(int(self._left_msg[index])))
        right = None
        if self._right_msg is not None:
            right = self._right_decode(cache.payload(int(self._right_msg[index])))
        exposure_ns = 0 if self._exposure_ns is None else int(self._exposure_ns[index])
        t_ns = int(self._frame_t_ns[index])
        return StereoFrame(t_ns, left, right, index, exposure_ns=exposure_ns)

    def frame(self, index: int) -> StereoFrame:
        if not 0 <= index < len(self._frame_t_ns):
            raise IndexError(f"frame {index} out of range (0..{len(self._frame_t_ns) - 1})")
        return self._decode(self._cache, index)

    def iter_frames(self) -> Iterator[StereoFrame]:
        """Stream frames in time order, decompressing each chunk once (dropped after last use)."""
        s = self.scan
        msg_lists = [self._left_msg] + ([self._right_msg] if self._right_msg is not None else [])
        chunk_of = np.stack([s.msg_chunk[m] for m in msg_lists])  # (1 or 2, n_frames)
        last_use: dict[int, int] = {}
        for i in range(chunk_of.shape[1]):
            for c in chunk_of[:, i]:
                last_use[int(c)] = i
        release: dict[int, list[int]] = {}
        for c, i in last_use.items():
            release.setdefault(i, []).append(c)
        cache = ChunkCache(s, max_chunks=1 << 30)
        skipped = 0
        try:
            for i in range(chunk_of.shape[1]):
                try:
                    frame = self._decode(cache, i)
                except CorruptChunk as exc:
                    if self.strict:
                        raise InputError(
                            f"{self.path}: {exc}; run without --strict to skip its frames"
                        ) from exc
                    if str(exc) not in self.warnings:
                        self.warn(str(exc))
                    skipped += 1
                else:
                    yield frame
                for c in release.get(i, ()):
                    cache.drop(c)
        finally:
            cache.close()
            if skipped:
                self.warn(f"{skipped} frame(s) in corrupt chunks were skipped while reading")

    def verify(self) -> int:
        """Read every lazily indexed (not yet CRC-checked) chunk once and drop the frames of
        the corrupt ones, so counts, spans and gaps are what a run will get (``iter_frames``
        skips the same frames). Returns how many chunks are corrupt (each also warned about).
        ``slam info`` calls this; a second call returns the first one's answer."""
        if self._corrupt_chunks is not None:
            return len(self._corrupt_chunks)
        cache = ChunkCache(self.scan, max_chunks=1)
        bad: list[int] = []
        try:
            for k, ref in enumerate(self.scan.chunks):
                if ref.validated:
                    continue
                try:
                    cache.chunk_data(k)
                except CorruptChunk as exc:
                    self.warn(str(exc))
                    bad.append(k)
        finally:
            cache.close()
        if bad:
            chunk = self.scan.msg_chunk
            lost = np.isin(chunk[self._left_msg], bad)
            if self._right_msg is not None:
                lost |= np.isin(chunk[self._right_msg], bad)
            if np.any(lost):
                t = self._frame_t_ns[lost]
                self.warn(
                    f"{int(lost.sum())} frame(s) in corrupt chunks will be skipped "
                    f"(t = {t[0] * 1e-9:.3f} .. {t[-1] * 1e-9:.3f} s)"
                )
                self._left_msg = self._left_msg[~lost]
                if self._right_msg is not None:
                    self._right_msg = self._right_msg[~lost]
                self._frame_t_ns = self._frame_t_ns[~lost]
                if self._exposure_ns is not None:
                    self._exposure_ns = self._exposure_ns[~lost]
        self._corrupt_chunks = bad
        return len(bad)

    def close(self) -> None:
        self._cache.close()

    def describe_topics(self) -> str:
        return self.scan.describe_topics()


def _decode_pose_generic(data: bytes, schema: str) -> tuple[int, np.ndarray, np.ndarray]:
    """Pose-like messages through rosbags' typestore -> (t_ns, position, q_wxyz)."""
    from rosbags.typesys import Stores, get_typestore

    msg: Any = get_typestore(Stores.ROS2_HUMBLE).deserialize_cdr(data, schema)
    stamp = msg.header.stamp
    t_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    if schema == "geometry_msgs/msg/TransformStamped":
        p, o = msg.transform.translation, msg.transform.rotation
    elif schema == "geometry_msgs/msg/PoseStamped":
        p, o = msg.pose.position, msg.pose.orientation
    else:  # Odometry, PoseWithCovarianceStamped: pose.pose
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
    return t_ns, np.array([p.x, p.y, p.z]), np.array([o.w, o.x, o.y, o.z])
