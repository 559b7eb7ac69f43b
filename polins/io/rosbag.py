"""ROS 1 / ROS 2 bags: ``sensor_msgs/Imu`` and raw polarization ``sensor_msgs/Image`` topics.

Needs the optional extra ``ros`` (``pip install 'polins[ros]'``, the pure-Python ``rosbags``
library; no ROS installation). ``rosbags`` is imported only when a bag is read or written.

Conventions
-----------
* Times: each message's ``header.stamp`` (the bag's record time only when the stamp is 0),
  as ``t = stamp - epoch_utc`` [s] on the log clock. Absolute stamps (UTC, after 2000) need
  no ``epoch_utc``: t = 0 is then the first stamp, floored to a whole second. Stamps before
  2000 (simulation or boot time) are ``t`` itself, and need ``epoch_utc``, the UTC time of
  stamp 0.
* ``sensor_msgs/Imu``: ``angular_velocity`` [rad/s] and ``linear_acceleration`` [m/s^2]
  are taken as the body-frame (FLU, REP-103) angular rate and specific force (REP-145);
  ``orientation`` is ignored.
* ``sensor_msgs/Image``: the raw DoFP mosaic, unpacked, one channel. Accepted encodings
  (case-insensitive): ``mono8``, ``mono16``, ``8UC1``, ``16UC1`` and polarized-mono names
  such as ``polarized_mono8``, ``polarized_mono12``, ``polarized_mono16``,
  ``polarization_mono16_90_45_135_0``; 10/12-bit data are expected unpacked in 16-bit words.
  The polarizer layout is taken from the camera model, never from the encoding name.
  Packed encodings (``mono12p``) are rejected with a message.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from polins.errors import UserInputError
from polins.io.images import ImageReadError, decode_image

_ENCODING = re.compile(
    r"^(?:(?:polari[sz]ed|polarization)_?)?mono_?(?P<bits>8|10|12|16)(?:_[0-9_]+)?$"
    r"|^(?P<cv>8|16)uc1$"
)
IMU_TYPE = "sensor_msgs/msg/Imu"
# stamps before this are not absolute UTC times (simulation or boot time)
ABSOLUTE_AFTER = pd.Timestamp("2000-01-01", tz="UTC")
IMAGE_TYPE = "sensor_msgs/msg/Image"


def _rosbags() -> Any:
    try:
        import rosbags
    except ImportError:
        raise ImportError(
            "ROS bag support needs the optional extra 'ros': pip install 'polins[ros]' "
            "(installs the pure-Python 'rosbags' library)"
        ) from None
    import rosbags.highlevel
    import rosbags.typesys

    return rosbags


def encoding_dtype(encoding: str) -> np.dtype:
    """Pixel dtype of a supported raw-mosaic encoding; ``ImageReadError`` otherwise."""
    match = _ENCODING.match(encoding.strip().lower())
    if match is None:
        hint = " (packed formats must be unpacked to 16 bit)" if "p" in encoding[-2:] else ""
        raise ImageReadError(
            f"unsupported image encoding {encoding!r}{hint}: expected mono8, mono16, 8UC1, "
            "16UC1 or a polarized mono encoding (e.g. polarized_mono16)"
        )
    bits = int(match.group("bits") or match.group("cv"))
    return np.dtype(np.uint8 if bits == 8 else np.uint16)


@dataclass(frozen=True)
class ImageMessage:
    """A raw ``sensor_msgs/Image`` payload (picklable; decoded in a worker if need be)."""

    encoding: str
    height: int
    width: int
    step: int
    is_bigendian: int
    data: bytes
    source: str

    def to_array(self, shape: tuple[int, int] | None = None) -> NDArray[np.unsignedinteger]:
        """Decode to an ``(H, W)`` mosaic; ``ImageReadError`` for any inconsistency."""
        dtype = encoding_dtype(self.encoding)
        row_bytes = self.width * dtype.itemsize
        if self.height <= 0 or self.width <= 0 or self.step < row_bytes:
            raise ImageReadError(
                f"{self.source}: bad image geometry {self.height}x{self.width}, step {self.step}"
            )
        if len(self.data) < self.height * self.step:
            raise ImageReadError(
                f"{self.source}: image data has {len(self.data)} bytes, "
                f"{self.height * self.step} expected (truncated message)"
            )
        buf = np.frombuffer(self.data, dtype=np.uint8, count=self.height * self.step)
        rows = buf.reshape(self.height, self.step)[:, :row_bytes]
        wire = dtype.newbyteorder(">" if self.is_bigendian else "<")
        raw = np.ascontiguousarray(rows).view(wire).reshape(self.height, self.width)
        return decode_image(raw.astype(dtype, copy=False), self.source, shape)


@dataclass(frozen=True, eq=False)
class BagImages:
    """Image topic of a bag: times, and lazy iteration over :class:`ImageMessage` items."""

    path: Path
    topic: str
    t: NDArray[np.float64]
    epoch_utc: pd.Timestamp

    def __len__(self) -> int:
        return len(self.t)

    def __iter__(self) -> Iterator[tuple[float, ImageMessage]]:
        rb = _rosbags()
        with rb.highlevel.AnyReader([self.path], default_typestore=_typestore(1)) as reader:
            conns = [c for c in reader.connections if c.topic == self.topic]
            for k, (conn, _, rawdata) in enumerate(reader.messages(connections=conns)):
                msg = reader.deserialize(rawdata, conn.msgtype)
                yield (
                    float(self.t[k]),
                    ImageMessage(
                        encoding=str(msg.encoding),
                        height=int(msg.height),
                        width=int(msg.width),
                        step=int(msg.step),
                        is_bigendian=int(msg.is_bigendian),
                        data=bytes(msg.data),
                        source=f"{self.path}:{self.topic}#{k}",
                    ),
                )


def _typestore(ros_version: int) -> Any:
    rb = _rosbags()
    stores = rb.typesys.Stores
    return rb.typesys.get_typestore(stores.ROS1_NOETIC if ros_version == 1 else stores.ROS2_HUMBLE)


def _stamp_ns(msg: Any, record_ns: int) -> int:
    ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
    return ns if ns != 0 else int(record_ns)


def _bag_path(path: Path) -> Path:
    if path.suffix in (".mcap", ".db3") and (path.parent / "metadata.yaml").is_file():
        return path.parent  # a ROS 2 storage file: the bag is its folder
    return path


def _pick_topic(reader: Any, msgtype: str, topic: str | None, what: str, path: Path) -> str:
    topics = {c.topic: c.msgtype for c in reader.connections}
    if topic is not None:
        if topic not in topics:
            raise UserInputError(f"{path}: no topic {topic!r}; topics: {topics}")
        if topics[topic] != msgtype:
            raise UserInputError(f"{path}: topic {topic!r} is {topics[topic]}, expected {msgtype}")
        return topic
    found = sorted(t for t, typ in topics.items() if typ == msgtype)
    if len(found) != 1:
        raise UserInputError(
            f"{path}: {'no' if not found else 'several'} {msgtype} topic(s) {found}; "
            f"name the {what} topic (manifest [ros] {what}_topic)"
        )
    return found[0]


def _pick_topics(
    reader: Any, imu_topic: str | None, image_topic: str | None, path: Path
) -> tuple[str, str]:
    return (_pick_topic(reader, IMU_TYPE, imu_topic, "imu", path),
            _pick_topic(reader, IMAGE_TYPE, image_topic, "image", path))  # fmt: skip


def bag_topics(
    path: str | Path, imu_topic: str | None = None, image_topic: str | None = None
) -> tuple[str, str]:
    """The IMU and image topics of a bag: the ones named (checked), else the only topic of
    type ``sensor_msgs/Imu`` / ``sensor_msgs/Image`` (one-line ``UserInputError`` listing the
    topics when there is none or several)."""
    rb = _rosbags()
    path = _bag_path(Path(path))
    if not path.exists():
        raise FileNotFoundError(f"bag not found: {path}")
    try:
        with rb.highlevel.AnyReader([path], default_typestore=_typestore(1)) as reader:
            return _pick_topics(reader, imu_topic, image_topic, path)
    except rb.highlevel.AnyReaderError as exc:
        raise UserInputError(f"{path}: not a readable ROS bag: {exc}") from None


def read_bag(
    path: str | Path,
    *,
    epoch_utc: Any = None,
    imu_topic: str | None = None,
    image_topic: str | None = None,
) -> tuple[pd.DataFrame, BagImages]:
    """Read the IMU samples and the image index of a ROS 1 or ROS 2 bag.

    Parameters
    ----------
    path : str or Path
        ROS 1 ``.bag`` file, or ROS 2 bag folder (or its ``.mcap`` / ``.db3`` file).
    epoch_utc : timezone-aware time, optional
        ``t = 0``; default: the first message stamp, floored to a whole second
        (available as ``images.epoch_utc``), when the stamps are absolute UTC times
        (after 2000). Stamps before 2000 count from ``epoch_utc`` (required for them).
    imu_topic, image_topic : str, optional
        Default: the only topic of type ``sensor_msgs/Imu`` / ``sensor_msgs/Image``.

    Returns
    -------
    imu : DataFrame
        ``t, gx, gy, gz`` [rad/s], ``ax, ay, az`` [m/s^2], in bag order.
    images : BagImages
        Image times ``.t`` [s] and lazy iteration; images are decoded on use.
    """
    from polins.site import utc_timestamp

    rb = _rosbags()
    path = _bag_path(Path(path))
    if not path.exists():
        raise FileNotFoundError(f"bag not found: {path}")
    rows: list[tuple[int, float, float, float, float, float, float]] = []
    image_ns: list[int] = []
    try:
        reader_cm = rb.highlevel.AnyReader([path], default_typestore=_typestore(1))
        with reader_cm as reader:
            imu_topic, image_topic = _pick_topics(reader, imu_topic, image_topic, path)
            for conn, record_ns, rawdata in reader.messages(
                connections=[c for c in reader.connections if c.topic in (imu_topic, image_topic)]
            ):
                msg = reader.deserialize(rawdata, conn.msgtype)
                ns = _stamp_ns(msg, record_ns)
                if conn.topic == imu_topic:
                    w, a = msg.angular_velocity, msg.linear_acceleration
                    rows.append((ns, w.x, w.y, w.z, a.x, a.y, a.z))
                else:
                    image_ns.append(ns)
    except rb.highlevel.AnyReaderError as exc:
        raise UserInputError(f"{path}: not a readable ROS bag: {exc}") from None
    if not rows:
        raise UserInputError(f"{path}: topic {imu_topic!r} has no messages")
    first = min([rows[0][0], *image_ns[:1]])
    absolute = first >= ABSOLUTE_AFTER.value
    if epoch_utc is not None:
        epoch = utc_timestamp(epoch_utc)
    elif absolute:
        epoch = pd.Timestamp(first // 1_000_000_000 * 1_000_000_000, unit="ns", tz="UTC")
    else:
        raise UserInputError(
            f"{path}: the stamps start at {first / 1e9:.3f} s, not an absolute UTC time "
            "(simulation or boot time): give the UTC time of stamp 0 (manifest log.epoch_utc, "
            "polins manifest --epoch)"
        )
    epoch_ns = int(epoch.value) if absolute else 0  # relative stamps count from the epoch
    arr = np.array([r[1:] for r in rows], dtype=float)
    imu = pd.DataFrame(arr, columns=["gx", "gy", "gz", "ax", "ay", "az"])
    imu.insert(0, "t", np.array([(r[0] - epoch_ns) / 1e9 for r in rows]))
    t_img = np.array([(ns - epoch_ns) / 1e9 for ns in image_ns], dtype=float)
    return imu, BagImages(path=path, topic=image_topic, t=t_img, epoch_utc=epoch)


def write_bag(
    path: str | Path,
    imu: pd.DataFrame,
    images: Iterable[tuple[float, NDArray[np.unsignedinteger]]],
    *,
    epoch_utc: Any,
    ros_version: Literal[1, 2] = 2,
    imu_topic: str = "/imu/data",
    image_topic: str = "/camera/image_raw",
    encoding: str | None = None,
    imu_frame: str = "imu_link",
    camera_frame: str = "camera",
) -> Path:
    """Write IMU samples and raw images as a ROS 1 ``.bag`` or a ROS 2 bag folder.

    Messages go in time order; record time = header stamp = ``epoch_utc + t``. ``encoding``
    defaults to ``mono8`` / ``mono16`` by dtype (a polarized-mono name may be given).
    The bag must not exist yet (``rosbags`` never overwrites).
    """
    from polins.site import utc_timestamp

    _rosbags()
    path = Path(path)
    epoch_ns = int(utc_timestamp(epoch_utc).value)
    store = _typestore(ros_version)
    types = store.types
    header_t, time_t = types["std_msgs/msg/Header"], types["builtin_interfaces/msg/Time"]
    vec_t, quat_t = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Quaternion"]
    imu_t, image_t = types[IMU_TYPE], types[IMAGE_TYPE]

    def header(ns: int, frame: str) -> Any:
        stamp = time_t(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        if ros_version == 1:
            return header_t(seq=0, stamp=stamp, frame_id=frame)
        return header_t(stamp=stamp, frame_id=frame)

    def to_ns(t: float) -> int:
        return epoch_ns + round(t * 1e9)

    writer: Any
    if ros_version == 1:
        import rosbags.rosbag1 as rosbag1

        writer = rosbag1.Writer(path)

        def serialize(msg: Any, typ: str) -> Any:
            return store.serialize_ros1(msg, typ)
    else:
        import rosbags.rosbag2 as rosbag2

        writer = rosbag2.Writer(path, version=9)

        def serialize(msg: Any, typ: str) -> Any:
            return store.serialize_cdr(msg, typ)

    cols = imu.loc[:, ["t", "gx", "gy", "gz", "ax", "ay", "az"]].to_numpy(dtype=float)
    zero9 = np.zeros(9)
    with writer:
        c_imu = writer.add_connection(imu_topic, IMU_TYPE, typestore=store)
        c_img = writer.add_connection(image_topic, IMAGE_TYPE, typestore=store)
        k = 0

        def flush_imu(until: float) -> int:
            nonlocal k
            while k < len(cols) and cols[k, 0] <= until:
                row = cols[k]
                ns = to_ns(row[0])
                msg = imu_t(
                    header=header(ns, imu_frame),
                    orientation=quat_t(x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.r_[-1.0, np.zeros(8)],  # REP-145: no orientation
                    angular_velocity=vec_t(x=row[1], y=row[2], z=row[3]),
                    angular_velocity_covariance=zero9,
                    linear_acceleration=vec_t(x=row[4], y=row[5], z=row[6]),
                    linear_acceleration_covariance=zero9,
                )
                writer.write(c_imu, ns, serialize(msg, IMU_TYPE))
                k += 1
            return k

        for t, raw in images:
            raw = np.asarray(raw)
            if raw.ndim != 2 or raw.dtype not in (np.uint8, np.uint16):
                raise UserInputError(
                    f"raw image must be 2-D uint8/uint16, got {raw.shape} {raw.dtype}"
                )
            enc = encoding or ("mono8" if raw.dtype == np.uint8 else "mono16")
            if encoding_dtype(enc) != raw.dtype:
                raise UserInputError(f"encoding {enc!r} does not match image dtype {raw.dtype}")
            flush_imu(float(t))
            ns = to_ns(float(t))
            data = np.ascontiguousarray(raw.astype(raw.dtype.newbyteorder("<"), copy=False))
            msg = image_t(
                header=header(ns, camera_frame),
                height=raw.shape[0],
                width=raw.shape[1],
                encoding=enc,
                is_bigendian=0,
                step=raw.shape[1] * raw.dtype.itemsize,
                data=data.view(np.uint8).ravel(),
            )
            writer.write(c_img, ns, serialize(msg, IMAGE_TYPE))
        flush_imu(np.inf)
    return path


__all__ = ["ABSOLUTE_AFTER", "BagImages", "ImageMessage", "bag_topics", "encoding_dtype",
           "read_bag", "write_bag"]  # fmt: skip
