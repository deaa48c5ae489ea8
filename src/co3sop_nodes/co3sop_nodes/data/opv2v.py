"""OPV2V folders (as OpenCOOD reads them) and Co3SOP voxel labels: write and read (ROS-free).

Layout (see src/co3sop_nodes/doc/opv2v-format.md for the sources):

    <root>/<split>/<scenario>/data_protocol.yaml
    <root>/<split>/<scenario>/<cav_id>/<ts>.yaml, <ts>.pcd, <ts>_camera0..3.png
    <root>/additional_{25m,50m,76m}/<split>/<scenario>/<cav_id>/<ts>_voxels.npz   (key "voxels", uint8 [x][y][z])

Files are in CARLA's left-handed axes; CavFrame is REP-103. The conversion
happens here, through geometry.carla_*, and nowhere else. Every reading error
is a DatasetError that names the file and what is wrong with it.
"""

from __future__ import annotations

import os
import re
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
import yaml
from PIL import Image

from co3sop_nodes.common import geometry as geo
from co3sop_nodes.common.classes import IGNORE, NUM_CLASSES
from co3sop_nodes.common.errors import DatasetError
from co3sop_nodes.common.frames import CameraFrame, CavFrame, OtherVehicle
from co3sop_nodes.common.grid import BENCHMARK_RANGES

CAMERAS = ("camera0", "camera1", "camera2", "camera3")
LABEL_FOLDERS = {"25.6m": "additional_25m", "51.2m": "additional_50m", "76.8m": "additional_76m"}
SPLITS = ("train", "validate", "test", "test_culvercity")
KMH = 3.6
_TS_YAML = re.compile(r"^(\d+)\.yaml$")
_PCD_HEADER = """# .PCD v0.7 - Point Cloud Data file format
VERSION 0.7
FIELDS x y z rgb
SIZE 4 4 4 4
TYPE F F F F
COUNT 1 1 1 1
WIDTH {n}
HEIGHT 1
VIEWPOINT 0 0 0 1 0 0 0
POINTS {n}
DATA ascii
"""


# --- writing ---------------------------------------------------------------------------------------

_Dumper = yaml.CSafeDumper if yaml.__with_libyaml__ else yaml.SafeDumper  # the same text, about 4x faster


def _carla_pose(world_from_x: np.ndarray) -> list[float]:
    return geo.carla_matrix_to_pose(geo.ros_to_carla_matrix(world_from_x))


def _matrix_list(m: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in m]


def frame_yaml(frame: CavFrame) -> dict:
    """The per-timestamp yaml content of one CAV, with every field OpenCDA writes."""
    lidar_carla = geo.ros_to_carla_matrix(frame.world_from_lidar)
    out: dict = {}
    for cam in frame.cameras:
        cam_carla = geo.ros_to_carla_matrix(cam.world_from_camera)
        out[cam.name] = {
            "cords": _carla_pose(cam.world_from_camera),
            "extrinsic": _matrix_list(np.linalg.inv(cam_carla) @ lidar_carla),  # lidar -> camera, CARLA axes
            "intrinsic": _matrix_list(cam.intrinsics),
        }
    predicted = frame.world_from_predicted if frame.world_from_predicted is not None else frame.world_from_vehicle
    plan = frame.plan.copy()
    plan[:, 1] *= -1  # world y to CARLA axes; speed stays
    out.update(
        ego_speed=float(frame.speed * KMH),
        lidar_pose=_carla_pose(frame.world_from_lidar),
        plan_trajectory=[[float(v) for v in p] for p in plan],
        predicted_ego_pos=_carla_pose(predicted),
        true_ego_pos=_carla_pose(frame.world_from_vehicle),
        vehicles={
            int(v.id): {
                "angle": _carla_pose(v.world_from_vehicle)[3:],
                "center": [float(v.center[0]), float(-v.center[1]), float(v.center[2])],
                "extent": [float(e) for e in v.extent],
                "location": _carla_pose(v.world_from_vehicle)[:3],
                "speed": float(v.speed * KMH),
            }
            for v in frame.vehicles
        },
    )
    return out


def write_pcd(path: Path, points: np.ndarray, intensity: np.ndarray) -> None:
    """Open3D-style ASCII PCD: x y z in CARLA axes, intensity packed into the red byte of rgb."""
    xyz = geo.ros_to_carla_points(points)
    red = np.rint(np.clip(intensity, 0, 1) * 255).astype(np.uint32) << 16
    data = np.column_stack([xyz, red.view(np.float32)])
    # np.savetxt(f, data, fmt="%.10g")'s text, formatted in one call instead of one per row (2-3x faster)
    text = ("%.10g %.10g %.10g %.10g\n" * len(data)) % tuple(data.ravel().tolist())
    with open(path, "w") as f:
        f.write(_PCD_HEADER.format(n=len(data)))
        f.write(text)


def write_png(path: Path, array: np.ndarray) -> None:
    Image.fromarray(array).save(path, compress_level=3)


def label_path(root: Path, range_name: str, split: str, scenario: str, cav_id: int, timestamp: int) -> Path:
    return Path(root, LABEL_FOLDERS[range_name], split, scenario, str(cav_id), f"{timestamp:06d}_voxels.npz")


def write_frame(root: Path, split: str, frame: CavFrame, scenario_dir: str | None = None) -> None:
    """Writes one CAV's files; `scenario_dir` overrides the folder name (e.g. a temporary one)."""
    folder = scenario_dir or frame.scenario
    cav_dir = Path(root, split, folder, str(frame.cav_id))
    cav_dir.mkdir(parents=True, exist_ok=True)
    ts = f"{frame.timestamp:06d}"
    with open(cav_dir / f"{ts}.yaml", "w") as f:
        yaml.dump(frame_yaml(frame), f, Dumper=_Dumper, default_flow_style=False)
    write_pcd(cav_dir / f"{ts}.pcd", frame.points, frame.intensity)
    for cam in frame.cameras:
        write_png(cav_dir / f"{ts}_{cam.name}.png", cam.rgb)
        if cam.depth is not None:  # extras OpenCOOD ignores: depth in mm (16 bit), semantic labels
            write_png(
                cav_dir / f"{ts}_{cam.name}_depth.png", np.clip(np.rint(cam.depth * 1000), 0, 65535).astype(np.uint16)
            )
        if cam.semantic is not None:
            write_png(cav_dir / f"{ts}_{cam.name}_semantic.png", cam.semantic)
    for range_name, labels in frame.labels.items():
        path = label_path(root, range_name, split, folder, frame.cav_id, frame.timestamp)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, voxels=geo.ros_to_carla_grid(labels))


# --- reading ---------------------------------------------------------------------------------------


class _Loader(yaml.CSafeLoader if yaml.__with_libyaml__ else yaml.SafeLoader):
    """Safe YAML with OpenCOOD's float resolver (accepts 1e-5 without a dot); libyaml's parser where PyYAML
    has it (several times faster than the pure-Python one, which took most of a dataset's loading time; same values)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?|[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+][0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def read_yaml(path: Path) -> dict:
    try:
        with open(path) as f:
            data = yaml.load(f, Loader=_Loader)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path}: malformed yaml ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a mapping of OPV2V fields, got {type(data).__name__}")
    return data


def _numbers(path: Path, data: dict, keys: tuple, shape: tuple[int, ...]) -> np.ndarray:
    """data[k0][k1]... as a float array of `shape`, or a DatasetError naming file and field."""
    node, name = data, ".".join(map(str, keys))
    for key in keys:
        if not isinstance(node, dict) or key not in node:
            raise DatasetError(f"{path}: missing field '{name}'")
        node = node[key]
    try:
        arr = np.asarray(node, dtype=float)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: field '{name}' must be numbers, got {node!r:.80}") from None
    if arr.shape != shape or not np.isfinite(arr).all():
        raise DatasetError(f"{path}: field '{name}' must be {shape or 'a'} finite number(s), got {node!r:.80}")
    return arr


def read_pcd(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) REP-103, intensity (N,)) from an ASCII PCD with x y z and rgb or intensity."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    header: dict[str, list[str]] = {}
    lines = raw.split(b"\n")
    body_start = None
    for i, line in enumerate(lines):
        text = line.decode("ascii", "replace").strip()
        if not text or text.startswith("#"):
            continue
        key, *values = text.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            body_start = i + 1
            break
    if body_start is None:
        raise DatasetError(f"{path}: truncated PCD header (no DATA line)")
    fields = header.get("FIELDS", [])
    if not {"x", "y", "z"} <= set(fields) or not ({"rgb", "intensity"} & set(fields)):
        raise DatasetError(f"{path}: PCD FIELDS must hold x y z and rgb or intensity, got {fields}")
    if header["DATA"] != ["ascii"]:
        raise DatasetError(f"{path}: PCD DATA {header['DATA']} not supported (OPV2V writes ascii)")
    try:
        n = int(header.get("POINTS", ["-1"])[0])
    except ValueError:
        raise DatasetError(f"{path}: PCD POINTS is not a number") from None
    body = b"\n".join(lines[body_start:])
    try:
        values = np.array(body.split(), dtype=np.float64) if body.strip() else np.zeros(0)
    except ValueError:
        raise DatasetError(f"{path}: PCD data holds something that is not a number") from None
    if values.size != n * len(fields):
        raise DatasetError(
            f"{path}: PCD declares {n} points of {len(fields)} fields but holds {values.size} values (truncated?)"
        )
    table = values.reshape(n, len(fields))
    xyz = table[:, [fields.index(c) for c in "xyz"]].astype(np.float32)
    if "intensity" in fields:
        intensity = table[:, fields.index("intensity")].astype(np.float32)
    else:  # Open3D packs intensity into the red byte of the float rgb
        packed = table[:, fields.index("rgb")].astype(np.float32).view(np.uint32)
        intensity = ((packed >> 16) & 0xFF).astype(np.float32) / 255.0
    return geo.carla_to_ros_points(xyz), intensity


def read_png(path: Path) -> np.ndarray:
    if not path.exists():
        raise DatasetError(f"{path}: missing image")
    try:
        with Image.open(path) as img:
            img.load()
            return np.asarray(img.convert("RGB") if img.mode not in ("RGB", "L", "I;16") else img)
    except (OSError, SyntaxError, ValueError) as exc:
        raise DatasetError(f"{path}: unreadable PNG ({exc})") from None


def read_labels(path: Path, range_name: str) -> np.ndarray:
    """A Co3SOP label grid (CARLA axes on disk) as REP-103 [x][y][z] uint8, checked against the range's grid. A grid
    larger than the range's is cropped as Co3SOP's `LoadOccupancy` crops it: x and y about the centre, z from the
    bottom (`voxels[(X - nx) // 2 : (X + nx) // 2, (Y - ny) // 2 : (Y + ny) // 2, :nz]`); a smaller one is refused."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if "voxels" not in data:
                raise DatasetError(f"{path}: no 'voxels' array (keys: {list(data.keys())})")
            voxels = data["voxels"]
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DatasetError(f"{path}: unreadable npz ({exc})") from None
    dims = BENCHMARK_RANGES[range_name].dims
    if voxels.ndim != 3 or any(have < want for have, want in zip(voxels.shape, dims)):
        raise DatasetError(
            f"{path}: voxels shape {voxels.shape} is smaller than the {range_name} grid {dims} (or not 3D)"
        )
    (big_x, big_y, _), (nx, ny, nz) = voxels.shape, dims
    voxels = voxels[(big_x - nx) // 2 : (big_x + nx) // 2, (big_y - ny) // 2 : (big_y + ny) // 2, :nz]
    if voxels.dtype != np.uint8:
        raise DatasetError(f"{path}: voxels dtype {voxels.dtype}, expected uint8")
    bad = np.setdiff1d(np.unique(voxels), [*range(NUM_CLASSES), IGNORE])
    if bad.size:
        raise DatasetError(f"{path}: unknown label value(s) {bad.tolist()} (labels are 0..23 or 255)")
    return geo.carla_to_ros_grid(voxels)


def scenario_timestamps(scenario_dir: Path) -> tuple[list[str], list[int]]:
    """CAV folders (OpenCOOD order: sorted as strings, ego first) and the timestamps they all share."""
    if not scenario_dir.is_dir():
        raise DatasetError(f"{scenario_dir}: not a scenario folder")
    cavs = sorted(p.name for p in scenario_dir.iterdir() if p.is_dir() and re.fullmatch(r"-?\d+", p.name))
    if not cavs:
        raise DatasetError(f"{scenario_dir}: no CAV folders (named by actor id)")
    per_cav = {}
    for cav in cavs:
        per_cav[cav] = sorted(int(m.group(1)) for f in os.listdir(scenario_dir / cav) if (m := _TS_YAML.match(f)))
        if not per_cav[cav]:
            raise DatasetError(f"{scenario_dir / cav}: no <timestamp>.yaml files")
    reference = per_cav[cavs[0]]
    for cav in cavs[1:]:
        missing = sorted(set(reference) ^ set(per_cav[cav]))
        if missing:
            raise DatasetError(
                f"{scenario_dir / cav}: timestamps differ from CAV {cavs[0]}'s: {', '.join(f'{t:06d}' for t in missing[:5])}"
                + (" ..." if len(missing) > 5 else "")
            )
    return cavs, reference


class CavFiles(NamedTuple):
    """Where one CAV's sensor files of one timestamp are (labels: label_path)."""

    yaml: Path
    images: dict[str, Path]  # camera name -> PNG
    pcd: Path


def cav_files(root: Path, split: str, scenario: str, cav: str, timestamp: int) -> CavFiles:
    cav_dir, ts = Path(root, split, scenario, cav), f"{timestamp:06d}"
    return CavFiles(
        cav_dir / f"{ts}.yaml", {name: cav_dir / f"{ts}_{name}.png" for name in CAMERAS}, cav_dir / f"{ts}.pcd"
    )


def _lidar_carla(path: Path, data: dict) -> np.ndarray:
    """The yaml's LiDAR pose as a 4x4 world_from_lidar in CARLA's axes."""
    return geo.carla_pose_to_matrix(_numbers(path, data, ("lidar_pose",), (6,)))


def read_lidar_pose(root: Path, split: str, scenario: str, cav: str, timestamp: int) -> np.ndarray:
    """A CAV's world_from_lidar (4x4, REP-103) at one timestamp, from its yaml alone (no sensor file is read)."""
    path = cav_files(root, split, scenario, cav, timestamp).yaml
    return geo.carla_to_ros_matrix(_lidar_carla(path, read_yaml(path)))


def cav_frame_files(root: Path, split: str, scenario: str, cav: str, timestamp: int, ranges=(), points: bool = True):
    """The files `read_cav_frame` reads for these arguments (labels that do not exist left out)."""
    files = cav_files(root, split, scenario, cav, timestamp)
    labels = [label_path(root, r, split, scenario, int(cav), timestamp) for r in ranges]
    return [files.yaml, *files.images.values(), *([files.pcd] if points else []), *(p for p in labels if p.exists())]


def read_cav_frame(
    root: Path, split: str, scenario: str, cav: str, timestamp: int, ranges=(), points: bool = True
) -> CavFrame:
    """One CAV's files at one timestamp; `points=False` skips the (slow, ASCII) point cloud."""
    files = cav_files(root, split, scenario, cav, timestamp)
    path = files.yaml
    data = read_yaml(path)
    lidar_carla = _lidar_carla(path, data)
    cameras = []
    for name in CAMERAS:
        if name not in data:
            raise DatasetError(f"{path}: missing camera '{name}'")
        extrinsic = _numbers(path, data, (name, "extrinsic"), (4, 4))  # lidar -> camera, CARLA axes
        world_from_camera = geo.carla_to_ros_matrix(lidar_carla @ np.linalg.inv(extrinsic))
        intrinsic = _numbers(path, data, (name, "intrinsic"), (3, 3))
        cameras.append(CameraFrame(name, world_from_camera, intrinsic, read_png(files.images[name])))
    xyz, intensity = read_pcd(files.pcd) if points else (np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
    vehicles = []
    for vid in data.get("vehicles") or {}:
        location = _numbers(path, data, ("vehicles", vid, "location"), (3,))
        angle = _numbers(path, data, ("vehicles", vid, "angle"), (3,))
        vehicles.append(
            OtherVehicle(
                int(vid),
                geo.carla_to_ros_matrix(geo.carla_pose_to_matrix(np.concatenate([location, angle]))),
                _numbers(path, data, ("vehicles", vid, "center"), (3,)) * [1, -1, 1],
                _numbers(path, data, ("vehicles", vid, "extent"), (3,)),
                float(_numbers(path, data, ("vehicles", vid, "speed"), ())) / KMH,
            )
        )
    try:
        plan = np.asarray(data.get("plan_trajectory") or np.zeros((0, 3)), dtype=float).reshape(-1, 3) * [1, -1, 1]
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: field 'plan_trajectory' must be a list of [x, y, speed]") from None
    labels = {}
    for range_name in ranges:
        lp = label_path(root, range_name, split, scenario, int(cav), timestamp)
        if lp.exists():
            labels[range_name] = read_labels(lp, range_name)
    return CavFrame(
        scenario=scenario,
        cav_id=int(cav),
        timestamp=timestamp,
        world_from_vehicle=geo.carla_to_ros_matrix(
            geo.carla_pose_to_matrix(_numbers(path, data, ("true_ego_pos",), (6,)))
        ),
        world_from_lidar=geo.carla_to_ros_matrix(lidar_carla),
        speed=float(_numbers(path, data, ("ego_speed",), ())) / KMH,
        cameras=cameras,
        points=xyz,
        intensity=intensity,
        labels=labels,
        vehicles=vehicles,
        plan=plan,
        world_from_predicted=geo.carla_to_ros_matrix(
            geo.carla_pose_to_matrix(_numbers(path, data, ("predicted_ego_pos",), (6,)))
        ),
    )


def find_scenarios(root: Path) -> list[tuple[str, str]]:
    """(split, scenario) pairs under an OPV2V root (or a single split folder given as root)."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: not a folder")
    out = []
    for split in SPLITS:
        if (root / split).is_dir():
            out += [
                (split, s.name) for s in sorted((root / split).iterdir()) if s.is_dir() and not s.name.startswith(".")
            ]
    if not out:
        raise DatasetError(f"{root}: no OPV2V split folders ({', '.join(SPLITS)}) with scenarios")
    return out


def read_scenario(
    root: Path, split: str, scenario: str, ranges=tuple(BENCHMARK_RANGES), points: bool = True
) -> Iterator[tuple[int, list[CavFrame] | DatasetError]]:
    """Per timestamp: every CAV's frame, or the DatasetError that made that timestamp unreadable."""
    cavs, timestamps = scenario_timestamps(Path(root, split, scenario))
    for ts in timestamps:
        try:
            yield ts, [read_cav_frame(root, split, scenario, cav, ts, ranges, points) for cav in cavs]
        except DatasetError as exc:
            yield ts, exc
