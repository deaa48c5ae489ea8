"""sensor_msgs: PointCloud2, Image, CameraInfo (ROS-free adapters; see backend.py).

A point layout is a numpy structured dtype; its PointFields are derived from it, so each layout is written
once: `LIDAR_POINTS` for the scans a bag carries, `LABEL_POINTS` for coloured voxel centres (viewers).
"""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.errors import Co3sopError, DatasetError
from co3sop_nodes.messages.backend import MessageTypes, octets_of
from co3sop_nodes.messages.std import header_msg

POINT_CLOUD = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"

# x, y, z (m), intensity, and the simulator's per-point class (0 where unknown)
LIDAR_POINTS = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "label"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "u1"],
        "offsets": [0, 4, 8, 12, 16],
        "itemsize": 20,
    }
)
# x, y, z (m), rgb (float32 holding 0x00RRGGBB, the PCL / RViz convention), label
LABEL_POINTS = np.dtype(
    {
        "names": ["x", "y", "z", "rgb", "label"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "u1"],
        "offsets": [0, 4, 8, 12, 16],
        "itemsize": 20,
    }
)

# sensor_msgs/PointField datatypes -> numpy
POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
_DATATYPE_OF = {np.dtype(t): d for d, t in POINT_FIELD_TYPES.items()}
# image encodings -> (channels, numpy dtype)
ENCODINGS = {"rgb8": (3, np.uint8), "mono8": (1, np.uint8), "32FC1": (1, np.dtype("<f4"))}


def point_fields(layout: np.dtype) -> list[tuple[str, int, int]]:
    """A point layout as PointField (name, offset, datatype) triples."""
    return [(name, offset, _DATATYPE_OF[dtype]) for name, (dtype, offset) in layout.fields.items()]


def point_cloud_msg(types: MessageTypes, points: np.ndarray, *, stamp_ns: int, frame_id: str):
    """(N,) structured array (a layout above) -> an unorganised, dense PointCloud2."""
    step = points.dtype.itemsize
    fields = [
        types.make("sensor_msgs/msg/PointField", name=name, offset=offset, datatype=datatype, count=1)
        for name, offset, datatype in point_fields(points.dtype)
    ]
    return types.make(
        POINT_CLOUD,
        header=header_msg(types, stamp_ns, frame_id),
        height=1,
        width=len(points),
        fields=fields,
        is_bigendian=False,
        point_step=step,
        row_step=step * len(points),
        data=types.octets(np.ascontiguousarray(points).view(np.uint8).reshape(-1)),
        is_dense=True,
    )


def points_of(msg, names: tuple[str, ...] = ("x", "y", "z")) -> np.ndarray:
    """(N,) structured view of the named fields of a little-endian PointCloud2, whatever else it carries;
    raises DatasetError when a field is missing or the data is short."""
    layout = {f.name: (f.offset, POINT_FIELD_TYPES.get(f.datatype)) for f in msg.fields}
    missing = [a for a in names if a not in layout or layout[a][1] is None]
    if missing:
        raise DatasetError(f"point cloud has no numeric {', '.join(missing)} field (fields: {', '.join(layout)})")
    if msg.is_bigendian:
        raise DatasetError("point cloud is big-endian; only little-endian clouds are read")
    data, n, step = octets_of(msg.data), msg.width * msg.height, msg.point_step
    if step <= 0 or len(data) < n * step:
        raise DatasetError(f"point cloud data holds {len(data)} bytes, {n} points of {step} bytes need {n * step}")
    dtype = np.dtype(
        {
            "names": list(names),
            "formats": [layout[a][1] for a in names],
            "offsets": [layout[a][0] for a in names],
            "itemsize": step,
        }
    )
    return np.frombuffer(data, dtype, count=n)


def xyz_of(msg) -> np.ndarray:
    """(N, 3) float32 x, y, z of a PointCloud2."""
    cloud = points_of(msg)
    return np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(np.float32)


def image_msg(types: MessageTypes, array: np.ndarray, encoding: str, *, stamp_ns: int, frame_id: str):
    """(H, W, 3) uint8 rgb8, (H, W) uint8 mono8 or (H, W) float32 32FC1 -> Image."""
    h, w = array.shape[:2]
    data = np.ascontiguousarray(array, ENCODINGS[encoding][1]).view(np.uint8).reshape(-1)
    return types.make(
        IMAGE,
        header=header_msg(types, stamp_ns, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=len(data) // h,
        data=types.octets(data),
    )


def image_of(msg, what: str) -> np.ndarray:
    """(H, W, C) or (H, W) view of an Image of a known encoding (rows may be padded to `step`); raises Co3sopError
    naming `what` (a topic or file) otherwise."""
    if msg.encoding not in ENCODINGS:
        raise Co3sopError(f"{what}: encoding {msg.encoding!r}, expected one of {', '.join(ENCODINGS)}")
    channels, dtype = ENCODINGS[msg.encoding]
    row = channels * np.dtype(dtype).itemsize * msg.width
    data = np.frombuffer(octets_of(msg.data), np.uint8)
    if msg.step < row or len(data) < msg.step * msg.height:
        raise Co3sopError(f"{what}: {len(data)} bytes do not hold {msg.height} rows of {msg.step} bytes")
    rows = data[: msg.step * msg.height].reshape(msg.height, msg.step)[:, :row]
    shape = (msg.height, msg.width, channels) if channels > 1 else (msg.height, msg.width)
    return np.ascontiguousarray(rows).view(dtype).reshape(shape) if dtype != np.uint8 else rows.reshape(shape)


def rgb_of(msg, what: str) -> np.ndarray:
    """(H, W, 3) uint8 of an rgb8 Image; raises Co3sopError naming `what` for another encoding."""
    if msg.encoding != "rgb8":
        raise Co3sopError(f"{what}: encoding {msg.encoding!r}, expected rgb8")
    return image_of(msg, what)


def camera_info_msg(
    types: MessageTypes, intrinsics: np.ndarray, width: int, height: int, *, stamp_ns: int, frame_id: str
):
    """A pinhole CameraInfo without distortion: K = intrinsics, R = I, P = [K | 0]."""
    p = np.zeros((3, 4))
    p[:, :3] = intrinsics
    return types.make(
        CAMERA_INFO,
        header=header_msg(types, stamp_ns, frame_id),
        height=height,
        width=width,
        distortion_model="plumb_bob",
        d=types.sequence(np.zeros(5), "float64"),
        k=types.fixed(intrinsics, "float64"),
        r=types.fixed(np.eye(3), "float64"),
        p=types.fixed(p, "float64"),
        binning_x=0,
        binning_y=0,
        roi=types.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def intrinsics_of(msg) -> np.ndarray:
    """A CameraInfo's K as (3, 3) float64."""
    return np.array(msg.k, np.float64).reshape(3, 3)
