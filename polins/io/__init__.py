"""Recorded logs: manifest, IMU tables, image folders, ROS bags and atomic outputs.

``write_log`` / ``read_log`` handle the log folder of docs/filter.md (see ``polins.io.log``
for the manifest format); ``polins.io.tables`` reads IMU CSV/Parquet with unit metadata;
``polins.io.images`` reads 16-bit PNG/TIFF raw mosaics and their timestamp index;
``polins.io.rosbag`` (optional extra ``ros``) reads and writes ROS 1/2 bags.
"""

from polins.io.atomic import atomic_path, write_text_atomic
from polins.io.images import (
    ImageIndex,
    ImageReadError,
    load_raw,
    read_image,
    read_image_index,
    time_from_name,
    write_image,
    write_image_index,
)
from polins.io.log import Log, ManifestError, parse_manifest, read_log, write_log
from polins.io.tables import read_imu, read_table, write_imu, write_table

__all__ = [
    "ImageIndex",
    "ImageReadError",
    "Log",
    "ManifestError",
    "atomic_path",
    "load_raw",
    "parse_manifest",
    "read_image",
    "read_image_index",
    "read_imu",
    "read_log",
    "read_table",
    "time_from_name",
    "write_image",
    "write_image_index",
    "write_imu",
    "write_log",
    "write_table",
    "write_text_atomic",
]
