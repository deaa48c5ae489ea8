"""OPV2V folders and Co3SOP labels: exact round trip, the hand-written fixture, and every bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from co3sop_nodes.common import geometry as geo
from co3sop_nodes.common.errors import Co3sopError, DatasetError
from co3sop_nodes.data import opv2v
from co3sop_nodes.sim.lidar import LidarConfig
from co3sop_nodes.sim.scenario import ScenarioConfig, simulate
from co3sop_nodes.sim.traffic import TrafficConfig

FIXTURE = Path(__file__).resolve().parents[2] / "fixtures" / "opv2v"
SCENARIO = "2021_08_24_21_29_28"


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """Two frames of a small simulated scenario, written to an OPV2V folder."""
    cfg = ScenarioConfig(
        traffic=TrafficConfig(cavs=2, vehicles=8, pedestrians=6),
        frames=2,
        warmup=5,
        image_size=(64, 48),
        lidar=LidarConfig(azimuth_steps=128),
        ranges=("51.2m",),
    )
    root = tmp_path_factory.mktemp("opv2v")
    frames = list(simulate(cfg, seed=3, name="2021_01_02_03_04_05"))
    for per_ts in frames:
        for frame in per_ts:
            opv2v.write_frame(root, "train", frame)
    return root, frames


def test_simulated_folder_reads_back_exactly(simulated):
    root, frames = simulated
    back = list(opv2v.read_scenario(root, "train", "2021_01_02_03_04_05", ("51.2m",)))
    assert [ts for ts, _ in back] == [f[0].timestamp for f in frames]
    for (_, read), written in zip(back, frames):
        assert not isinstance(read, Exception), read
        assert [f.cav_id for f in read] == sorted((f.cav_id for f in written), key=str)  # OpenCOOD order
        by_id = {f.cav_id: f for f in read}
        for w in written:
            r = by_id[w.cav_id]
            np.testing.assert_allclose(r.world_from_lidar, w.world_from_lidar, atol=1e-9)
            np.testing.assert_allclose(r.world_from_vehicle, w.world_from_vehicle, atol=1e-9)
            np.testing.assert_array_equal(r.points, w.points)  # float32 survives %.10g exactly
            np.testing.assert_array_equal(r.intensity, np.rint(w.intensity * 255).astype(np.float32) / 255)
            np.testing.assert_array_equal(r.labels["51.2m"], w.labels["51.2m"])
            for rc, wc in zip(r.cameras, w.cameras):
                assert rc.name == wc.name
                np.testing.assert_array_equal(rc.rgb, wc.rgb)
                np.testing.assert_allclose(rc.world_from_camera, wc.world_from_camera, atol=1e-9)
                np.testing.assert_allclose(rc.intrinsics, wc.intrinsics)
            assert r.speed == pytest.approx(w.speed)
            assert {v.id for v in r.vehicles} == {v.id for v in w.vehicles}


def test_written_files_follow_the_opv2v_layout(simulated):
    root, frames = simulated
    frame = frames[0][0]
    cav_dir = root / "train" / frame.scenario / str(frame.cav_id)
    ts = f"{frame.timestamp:06d}"
    names = {p.name for p in cav_dir.iterdir()}
    assert {f"{ts}.yaml", f"{ts}.pcd", *(f"{ts}_camera{i}.png" for i in range(4))} <= names
    data = opv2v.read_yaml(cav_dir / f"{ts}.yaml")
    assert set(data) >= {
        "camera0",
        "camera1",
        "camera2",
        "camera3",
        "ego_speed",
        "lidar_pose",
        "plan_trajectory",
        "predicted_ego_pos",
        "true_ego_pos",
        "vehicles",
    }
    assert set(data["camera0"]) == {"cords", "extrinsic", "intrinsic"}
    # camera0's extrinsic is lidar -> camera in CARLA axes: the LiDAR sits 3 m behind and 0.9 m above it
    np.testing.assert_allclose(np.array(data["camera0"]["extrinsic"])[:3, 3], [-3.0, 0.0, 0.9], atol=1e-9)
    pcd = (cav_dir / f"{ts}.pcd").read_text().splitlines()
    assert pcd[2] == "FIELDS x y z rgb" and pcd[10] == "DATA ascii"
    labels = np.load(opv2v.label_path(root, "51.2m", "train", frame.scenario, frame.cav_id, frame.timestamp))["voxels"]
    assert labels.dtype == np.uint8 and labels.shape == (256, 256, 24)
    # on disk in CARLA axes: y mirrored against the REP-103 grid
    np.testing.assert_array_equal(labels, frame.labels["51.2m"][:, ::-1, :])


def test_pcd_text_is_what_numpy_savetxt_writes(tmp_path):
    # the one-call formatting keeps the bytes of the writer it replaced
    rng = np.random.default_rng(0)
    points = (rng.normal(size=(500, 3)) * 40).astype(np.float32)
    intensity = rng.uniform(0, 1, 500).astype(np.float32)
    opv2v.write_pcd(tmp_path / "a.pcd", points, intensity)
    red = (np.rint(np.clip(intensity, 0, 1) * 255).astype(np.uint32) << 16).view(np.float32)
    with open(tmp_path / "b.pcd", "w") as f:
        f.write(opv2v._PCD_HEADER.format(n=500))
        np.savetxt(f, np.column_stack([geo.ros_to_carla_points(points), red]), fmt="%.10g")
    assert (tmp_path / "a.pcd").read_bytes() == (tmp_path / "b.pcd").read_bytes()


def test_hand_written_fixture_reads_as_the_format_says():
    cavs, timestamps = opv2v.scenario_timestamps(FIXTURE / "test" / SCENARIO)
    assert cavs == ["4805", "4814"] and timestamps == [69, 71]
    frame = opv2v.read_cav_frame(FIXTURE, "test", SCENARIO, "4805", 69, ("51.2m",))
    carla = geo.carla_pose_to_matrix([144.33, -388.89, 1.93, 0.078, 174.18048095703125, 0.21])
    np.testing.assert_allclose(frame.world_from_lidar, geo.carla_to_ros_matrix(carla), atol=1e-12)
    assert frame.world_from_lidar[1, 3] == pytest.approx(388.89)  # y flips at the boundary
    # PCD: CARLA y negated; intensity from the red byte of the packed rgb float
    np.testing.assert_allclose(frame.points[:2], [[5.0, -0.5, -1.8], [10.25, 2.0, -1.9]], atol=1e-6)
    np.testing.assert_allclose(frame.intensity, np.array([255, 128, 1, 0, 64, 200]) / 255, atol=1e-7)
    assert frame.speed == pytest.approx(18.13 / 3.6)
    assert frame.cameras[0].intrinsics[0, 0] == pytest.approx(335.639852470912)
    assert frame.cameras[0].rgb.shape == (6, 8, 3)
    # camera0 pose from the extrinsic: 3 m ahead of the LiDAR, 0.9 m lower, looking the same way
    lidar_from_camera = np.linalg.inv(frame.world_from_lidar) @ frame.cameras[0].world_from_camera
    np.testing.assert_allclose(lidar_from_camera[:3, 3], [3.0, 0.0, -0.9], atol=1e-5)
    labels = frame.labels["51.2m"]
    assert labels[105, 255 - 135, 3] == 10  # the vehicle at CARLA y > 0 is at REP-103 y < 0
    assert labels[105, 135, 3] == 0
    assert labels[0, 255, 23] == 255
    (other,) = frame.vehicles
    assert other.id == 4814 and other.extent.tolist() == [2.45, 1.06, 0.75]


def test_fixture_yaml_tolerates_exponents_without_a_dot(tmp_path):
    path = tmp_path / "x.yaml"
    path.write_text("ego_speed: 1e-5\n")
    assert opv2v.read_yaml(path)["ego_speed"] == pytest.approx(1e-5)


# --- bad input: every error names the file and says what is wrong ---------------------------------


@pytest.fixture
def broken(tmp_path):
    """A writable copy of the fixture to damage."""
    shutil.copytree(FIXTURE, tmp_path / "opv2v")
    return tmp_path / "opv2v"


def _cav(root: Path, cav: str = "4805") -> Path:
    return root / "test" / SCENARIO / cav


def _read(root: Path, cav: str = "4805", ts: int = 69):
    return opv2v.read_cav_frame(root, "test", SCENARIO, cav, ts, ("51.2m",))


def _expect(fn, path: Path, *words: str) -> None:
    with pytest.raises(DatasetError) as info:
        fn()
    message = str(info.value)
    assert isinstance(info.value, Co3sopError)
    assert str(path) in message, message
    for w in words:
        assert w in message, message


def test_malformed_yaml(broken):
    path = _cav(broken) / "000069.yaml"
    path.write_text("camera0: [unclosed\n")
    _expect(lambda: _read(broken), path, "malformed yaml")


def test_truncated_yaml_is_missing_fields(broken):
    path = _cav(broken) / "000069.yaml"
    path.write_text(path.read_text()[: len(path.read_text()) // 3].rsplit("\n", 1)[0] + "\n")
    _expect(lambda: _read(broken), path, "missing")


def test_yaml_field_of_the_wrong_shape(broken):
    path = _cav(broken) / "000069.yaml"
    path.write_text(path.read_text().replace("lidar_pose:\n- ", "lidar_pose:\n- - "))
    _expect(lambda: _read(broken), path, "lidar_pose")


def test_missing_camera_in_yaml(broken):
    path = _cav(broken) / "000069.yaml"
    text = path.read_text()
    start, end = text.index("camera2:"), text.index("camera3:")
    path.write_text(text[:start] + text[end:])
    _expect(lambda: _read(broken), path, "camera2")


def test_missing_camera_image(broken):
    path = _cav(broken) / "000069_camera3.png"
    path.unlink()
    _expect(lambda: _read(broken), path, "missing image")


def test_corrupt_png(broken):
    path = _cav(broken) / "000069_camera1.png"
    path.write_bytes(path.read_bytes()[:40])
    _expect(lambda: _read(broken), path, "unreadable PNG")


def test_truncated_pcd(broken):
    path = _cav(broken) / "000069.pcd"
    path.write_text(path.read_text()[:-30])
    _expect(lambda: _read(broken), path, "truncated")


def test_pcd_without_header(broken):
    path = _cav(broken) / "000069.pcd"
    path.write_text("1 2 3 4\n")
    _expect(lambda: _read(broken), path, "header")


def test_pcd_with_garbage(broken):
    path = _cav(broken) / "000069.pcd"
    path.write_text(path.read_text().replace("10.25", "ten"))
    _expect(lambda: _read(broken), path, "not a number")


def test_truncated_npz(broken):
    path = opv2v.label_path(broken, "51.2m", "test", SCENARIO, 4805, 69)
    path.write_bytes(path.read_bytes()[:100])
    _expect(lambda: _read(broken), path, "unreadable npz")


def test_npz_without_voxels_key(broken):
    path = opv2v.label_path(broken, "51.2m", "test", SCENARIO, 4805, 69)
    np.savez_compressed(path, labels=np.zeros((256, 256, 24), np.uint8))
    _expect(lambda: _read(broken), path, "'voxels'")


def test_npz_of_the_wrong_grid(broken):
    path = opv2v.label_path(broken, "51.2m", "test", SCENARIO, 4805, 69)
    np.savez_compressed(path, voxels=np.zeros((256, 256, 16), np.uint8))
    _expect(lambda: _read(broken), path, "is smaller than the 51.2m grid")


def test_unknown_label_value(broken):
    path = opv2v.label_path(broken, "51.2m", "test", SCENARIO, 4805, 69)
    voxels = np.zeros((256, 256, 24), np.uint8)
    voxels[1, 2, 3] = 77
    np.savez_compressed(path, voxels=voxels)
    _expect(lambda: _read(broken), path, "unknown label value", "77")


def test_cav_folder_missing_timestamps(broken):
    (_cav(broken, "4814") / "000071.yaml").unlink()
    _expect(lambda: opv2v.scenario_timestamps(broken / "test" / SCENARIO), _cav(broken, "4814"), "000071")


def test_read_scenario_reports_bad_timestamps_and_keeps_the_good(broken):
    (_cav(broken) / "000071_camera0.png").unlink()
    results = dict(opv2v.read_scenario(broken, "test", SCENARIO, ("51.2m",)))
    assert isinstance(results[71], DatasetError) and "camera0" in str(results[71])
    assert [f.cav_id for f in results[69]] == [4805, 4814]


def test_not_a_dataset(tmp_path):
    _expect(lambda: opv2v.find_scenarios(tmp_path), tmp_path, "no OPV2V split folders")


def test_label_grids_larger_than_the_range_are_cropped_as_co3sop_loads_them(tmp_path):
    """Co3SOP's LoadOccupancy: voxels[(X - nx) // 2 : (X + nx) // 2, (Y - ny) // 2 : (Y + ny) // 2, :nz] of the file."""
    from co3sop_nodes.common.grid import BENCHMARK_RANGES

    nx, ny, nz = BENCHMARK_RANGES["51.2m"].dims
    big = np.random.default_rng(0).integers(0, 24, (nx + 7, ny + 4, nz + 3), dtype=np.uint8)
    np.savez(tmp_path / "big.npz", voxels=big)
    want = big[3 : 3 + nx, 2 : 2 + ny, :nz]  # (X - nx) // 2 = 3, (Y - ny) // 2 = 2, z from the bottom
    assert np.array_equal(opv2v.read_labels(tmp_path / "big.npz", "51.2m"), geo.carla_to_ros_grid(want))
    np.savez(tmp_path / "exact.npz", voxels=want)
    assert np.array_equal(opv2v.read_labels(tmp_path / "exact.npz", "51.2m"), geo.carla_to_ros_grid(want))
    np.savez(tmp_path / "small.npz", voxels=want[:, :-1])
    with pytest.raises(DatasetError, match=r"small.npz: voxels shape .* is smaller than the 51.2m grid"):
        opv2v.read_labels(tmp_path / "small.npz", "51.2m")
