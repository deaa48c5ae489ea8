"""The dataset tools as users run them: generate, convert, info, voxelize (installed executables, real bags)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from executables import executable
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from co3sop_nodes.common import topics
from co3sop_nodes.data import bags, opv2v
from co3sop_nodes.inference.inputs import camera_inputs, sensor_inputs
from co3sop_nodes.messages import RosbagsTypes, occupancy_msg
from co3sop_nodes.model.config import preset

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "opv2v"
SCENARIO = "2021_08_24_21_29_28"


def tool(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([executable(args[0]), *args[1:]], capture_output=True, text=True, timeout=timeout)


def assert_bag_matches_folder(bag: Path, root: Path, split: str, scenario: str, ranges) -> int:
    """Every array in the bag equals the folder's (read through opv2v), and a camera model's inputs built from the
    bag's messages and mounts (as `vehicle` builds them) equal those built from the folder (as training does);
    returns the frames compared."""
    folder = {ts: frames for ts, frames in opv2v.read_scenario(root, split, scenario, ranges)}
    mounts, cfg = bags.read_static_transforms(bag), preset("tiny")
    compared = 0
    for (stamp, cavs), (_, frames) in zip(bags.read_frames(bag), sorted(folder.items())):
        assert stamp == frames[0].stamp_ns
        for f in frames:
            entry = cavs[f.cav_id]
            np.testing.assert_allclose(entry["pose"], f.world_from_lidar, atol=1e-9)
            np.testing.assert_array_equal(entry["points"], f.points)
            np.testing.assert_array_equal(entry["intensity"], f.intensity)
            assert set(entry["labels"]) == set(f.labels)
            for r in f.labels:
                np.testing.assert_array_equal(entry["labels"][r], f.labels[r])
            for cam in f.cameras:
                np.testing.assert_array_equal(entry["cameras"][cam.name], cam.rgb)
            if f.cameras:
                lidar = topics.lidar_frame(f.cav_id)
                cameras = [
                    (name, rgb, entry["intrinsics"][name], mounts.lookup(lidar, entry["optical_frames"][name]))
                    for name, rgb in sorted(entry["cameras"].items())
                ]
                got = sensor_inputs(cfg, entry["pose"], cameras)
                images, lidar2img = camera_inputs(
                    sorted(f.cameras, key=lambda c: c.name), f.world_from_lidar, cfg.image_size
                )
                np.testing.assert_array_equal(got["images"], images)
                np.testing.assert_allclose(got["lidar2img"], lidar2img, rtol=1e-6, atol=1e-4)
            compared += 1
    assert compared == sum(len(f) for f in folder.values())
    first = folder[min(folder)]  # the first frame's scans are the bag's first, each a vehicle's as it reads it
    scans = bags.read_scans(bag, len(first) + 1)
    assert len(scans) == min(len(first) + 1, compared)
    assert all(any(np.array_equal(s, f.points) for f in first) for s in scans[: len(first)])
    return compared


def chunk_compressions(bag: Path) -> set[str]:
    """The compression of every chunk of a bag's MCAP file ("" for none)."""
    with open(next(bag.glob("*.mcap")), "rb") as f:
        return {chunk.compression for chunk in make_reader(f).get_summary().chunk_indexes}


def test_convert_real_format_fixture_round_trip(tmp_path):
    result = tool("convert", str(FIXTURE), "--out", str(tmp_path / "bags"))
    assert result.returncode == 0, result.stderr
    bag = tmp_path / "bags" / "test" / SCENARIO
    assert assert_bag_matches_folder(bag, FIXTURE, "test", SCENARIO, ("51.2m",)) == 4
    assert chunk_compressions(bag) == {""}  # as ros2 bag record writes, unless --compress
    assert not list((tmp_path / "bags" / "test").glob(".*partial*"))


def test_bag_opens_without_this_package(tmp_path):
    """ros2 bag / Foxglove read the embedded schemas: no co3sop typestore is needed."""
    assert tool("convert", str(FIXTURE), "--out", str(tmp_path)).returncode == 0
    bag = tmp_path / "test" / SCENARIO
    with AnyReader([bag]) as reader:  # no default typestore: types only from the bag
        conns = {c.topic: c for c in reader.connections}
        gt = conns["/cav_4805/ground_truth/occupancy_50m"]
        assert gt.msgtype == "co3sop_msgs/msg/SemanticOccupancy"
        _, _, raw = next(reader.messages(connections=[gt]))
        msg = reader.deserialize(raw, gt.msgtype)
        assert (msg.grid.nx, msg.grid.ny, msg.grid.nz) == (256, 256, 24) and msg.header.frame_id == "cav_4805/lidar"
        assert conns["/cav_4805/camera0/image_raw"].msgtype == "sensor_msgs/msg/Image"
        assert conns["/tf_static"].msgtype == "tf2_msgs/msg/TFMessage"
    (mcap_file,) = bag.glob("*.mcap")
    with open(mcap_file, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary.statistics.message_count > 0
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    assert "metadata.yaml" in {p.name for p in bag.iterdir()}


@pytest.fixture
def damaged(tmp_path):
    root = tmp_path / "opv2v"
    shutil.copytree(FIXTURE, root)
    png = root / "test" / SCENARIO / "4814" / "000071_camera2.png"
    png.write_bytes(b"not a png")
    return root, png


def test_convert_stops_before_writing_on_bad_input(damaged, tmp_path):
    root, png = damaged
    result = tool("convert", str(root), "--out", str(tmp_path / "bags"))
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert str(png) in result.stderr and "unreadable PNG" in result.stderr
    assert not (tmp_path / "bags" / "test" / SCENARIO).exists()
    assert not list((tmp_path / "bags").glob("**/*.mcap"))


def test_convert_can_skip_bad_frames_and_report_them(damaged, tmp_path):
    root, png = damaged
    result = tool("convert", str(root), "--out", str(tmp_path / "bags"), "--on-error", "skip")
    assert result.returncode == 0, result.stderr
    assert "timestamp 000071 skipped" in result.stdout and str(png) in result.stdout
    stamps = [stamp for stamp, _ in bags.read_frames(tmp_path / "bags" / "test" / SCENARIO)]
    assert len(stamps) == 1


def test_tools_explain_bad_paths_without_traceback(tmp_path):
    for args in (("info", str(tmp_path / "nothing")), ("convert", str(tmp_path), "--out", str(tmp_path / "o"))):
        result = tool(*args)
        assert result.returncode == 2 and "error:" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize(
    "option",
    [
        ("--frames", "0"),
        ("--image-size", "0x48"),
        ("--lidar-steps", "-1"),
        ("--vehicles", "-1"),
        ("--workers", "0"),
        ("--cavs", "0"),
    ],
)
def test_generate_refuses_impossible_settings_before_writing(tmp_path, option):
    result = tool("generate", "--out", str(tmp_path / "data"), "--splits", "test=1", *option)
    assert result.returncode == 2 and result.stderr.startswith(f"generate: error: {option[0]}"), result.stderr
    assert "Traceback" not in result.stderr and not (tmp_path / "data").exists()


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    out = tmp_path_factory.mktemp("gen")
    args = (
        "generate",
        "--out",
        str(out / "data"),
        "--splits",
        "train=1",
        "test=1",
        "--frames",
        "2",
        "--cavs",
        "2",
        "--image-size",
        "64x48",
        "--lidar-steps",
        "128",
        "--vehicles",
        "10",
        "--bags",
        str(out / "bags"),
        "--compress-bags",
        "--pictures",
    )
    first = tool(*args)
    assert first.returncode == 0, first.stderr
    return out, args, first


def test_generate_writes_folders_labels_bags_and_pictures(generated):
    out, _, first = generated
    scenarios = opv2v.find_scenarios(out / "data")
    assert [s for s, _ in scenarios] == ["train", "test"]
    assert "frames" in first.stderr  # the progress bar
    for split, name in scenarios:
        cavs, timestamps = opv2v.scenario_timestamps(out / "data" / split / name)
        assert len(cavs) == 2 and timestamps == [70, 72]
        assert (out / "data" / split / name / "data_protocol.yaml").is_file()
        for folder in opv2v.LABEL_FOLDERS.values():
            assert (out / "data" / folder / split / name / cavs[0] / "000070_voxels.npz").is_file()
        assert len(list((out / "data" / "pictures" / split / name).glob("*/*.png"))) == 4
        assert_bag_matches_folder(out / "bags" / split / name, out / "data", split, name, tuple(opv2v.LABEL_FOLDERS))
        assert chunk_compressions(out / "bags" / split / name) == {"zstd"}  # --compress-bags
    assert not list((out / "data").glob("**/.*partial*"))


def test_generate_resumes_and_skips_complete_scenarios(generated):
    out, args, _ = generated
    split, name = opv2v.find_scenarios(out / "data")[0]
    # an interrupted scenario leaves only its staging folder: it is redone, the complete one skipped
    shutil.rmtree(out / "data" / split / name)
    (out / "data" / ".partial" / split / name / split / name).mkdir(parents=True)
    result = tool(*args)
    assert result.returncode == 0, result.stderr
    assert "1 scenario(s) to simulate, 1 already complete" in result.stdout
    assert (out / "data" / split / name).is_dir() and not (out / "data" / ".partial").exists()


def descendants(pid: int) -> set[int]:
    """Every process below `pid` (from /proc: no psutil here)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.add(child)
            todo.append(child)
    return found


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("how", ["SIGINT to the group (Ctrl-C)", "SIGTERM to generate"])
def test_generate_stops_every_worker_and_leaves_no_debris_in_the_splits(tmp_path, how):
    """Interrupted mid-scenario: no process left, nothing in a split or label folder (unfinished scenarios are
    in OUT/.partial, where OPV2V loaders do not look), and a re-run completes the dataset."""
    args = (
        "generate",
        "--out",
        str(tmp_path / "data"),
        "--splits",
        "train=2",
        "--frames",
        "8",
        "--cavs",
        "2",
        "--image-size",
        "64x48",
        "--lidar-steps",
        "128",
        "--vehicles",
        "10",
        "--workers",
        "2",
    )
    # SIGINT as a terminal delivers it: a test run started in the background (`&`) inherits SIGINT ignored
    proc = subprocess.Popen(
        [executable(args[0]), *args[1:]],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    staging = tmp_path / "data" / ".partial" / "train"
    deadline = time.monotonic() + 240
    while (
        len({p.relative_to(staging).parts[0] for p in staging.glob("*/train/*/*/*.yaml")}) < 2
    ):  # both workers writing frames
        assert proc.poll() is None and time.monotonic() < deadline, (
            proc.stdout.read() if proc.poll() is not None else "no frame written"
        )
        time.sleep(0.2)
    workers = descendants(proc.pid)
    assert len(workers) >= 3  # the pool's two workers and the manager
    if how.startswith("SIGINT"):
        os.killpg(proc.pid, signal.SIGINT)
    else:
        proc.send_signal(signal.SIGTERM)
    output = proc.communicate(timeout=60)[0]
    assert proc.returncode == 130 and "interrupted" in output and "Traceback" not in output, output
    time.sleep(0.5)
    assert not [pid for pid in workers if alive(pid)], "workers still running after generate stopped"
    folders = [tmp_path / "data" / "train", *(tmp_path / "data" / f / "train" for f in opv2v.LABEL_FOLDERS.values())]
    assert not [p for f in folders if f.exists() for p in f.iterdir()], "an unfinished scenario in a split folder"
    assert staging.is_dir()
    if how.startswith("SIGINT"):
        return  # resuming is the same after either signal: checked once

    again = tool(*args)
    assert again.returncode == 0 and "2 scenario(s) to simulate, 0 already complete" in again.stdout, again.stderr
    assert len(opv2v.find_scenarios(tmp_path / "data")) == 2 and not (tmp_path / "data" / ".partial").exists()


def test_info_summarises_folders_and_bags(generated):
    out, _, _ = generated
    folder = tool("info", str(out / "data"))
    assert folder.returncode == 0, folder.stderr
    assert "2 scenario(s)" in folder.stdout and "| 7 road |" in folder.stdout and "25.6m" in folder.stdout
    bag = tool("info", str(out / "bags"))
    assert bag.returncode == 0, bag.stderr
    assert "sensor_msgs/msg/PointCloud2" in bag.stdout and "2 frames" in bag.stdout and "| 10 vehicle |" in bag.stdout


def test_voxelize_reproduces_the_benchmark_labels(generated):
    """Re-annotating at the 51.2 m benchmark's settings re-creates exactly the labels generate wrote."""
    out, _, _ = generated
    result = tool("voxelize", str(out / "data"), "--name", "additional_check", "--extent", "51.2", "--voxel", "0.2")
    assert result.returncode == 0, result.stderr
    written = sorted((out / "data" / "additional_50m").glob("*/*/*/*.npz"))
    assert written
    for path in written:
        again = out / "data" / "additional_check" / path.relative_to(out / "data" / "additional_50m")
        np.testing.assert_array_equal(np.load(again)["voxels"], np.load(path)["voxels"])


# --- damaged files: one line naming the file and what is wrong (exit 2), never a traceback ---------------------------


def _first_chunk_data(mcap: bytes) -> int:
    """Offset of the first chunk's compressed records (MCAP: opcode, u64 length, start, end, size, crc, compression)."""
    pos = 8
    while mcap[pos] != 0x06:
        pos += 9 + int.from_bytes(mcap[pos + 1 : pos + 9], "little")
    compression = pos + 9 + 28
    return compression + 4 + int.from_bytes(mcap[compression : compression + 4], "little") + 8


DAMAGES = {
    "truncated": lambda mcap, meta: (mcap[: len(mcap) // 2], meta),
    "corrupt-chunk": lambda mcap, meta: (
        mcap[: (at := _first_chunk_data(mcap))] + bytes(b ^ 0xFF for b in mcap[at : at + 8]) + mcap[at + 8 :],
        meta,
    ),
    "random-bytes": lambda mcap, meta: (np.random.default_rng(0).bytes(len(mcap)), meta),
    "bad-metadata": lambda mcap, meta: (mcap, "rosbag2_bagfile_information: [unclosed\n  : {"),
}


@pytest.fixture(scope="module")
def damaged_bags(generated, tmp_path_factory):
    out, _, _ = generated
    source = next((out / "bags").glob("*/*/metadata.yaml")).parent
    mcap, meta = next(source.glob("*.mcap")).read_bytes(), (source / "metadata.yaml").read_text()
    root = tmp_path_factory.mktemp("damaged")
    for name, damage in DAMAGES.items():
        bag = root / name
        bag.mkdir()
        data, text = damage(mcap, meta)
        (bag / f"{bag.name}.mcap").write_bytes(data)
        (bag / "metadata.yaml").write_text(text.replace(source.name, bag.name))
    return root


@pytest.mark.parametrize("command", ["info", "player"])
@pytest.mark.parametrize("damage", list(DAMAGES))
def test_damaged_bags_are_explained(damaged_bags, command, damage):
    done = tool(command, str(damaged_bags / damage), timeout=120)
    lines = [line for line in done.stderr.splitlines() if line.startswith(f"{command}: error:")]
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert len(lines) == 1 and f"{damage}: damaged or not a rosbag2 bag: " in lines[0], done.stderr


def _recording(path: Path, malformed_at: int | None) -> Path:
    """A recording of 3 predictions and their ground truth; the prediction at `malformed_at` is not valid CDR."""
    from co3sop_nodes.common.grid import BENCHMARK_RANGES
    from co3sop_nodes.data.recording import McapRecorder
    from co3sop_nodes.v2x.codec import encode_labels

    grid, store = BENCHMARK_RANGES["51.2m"], bags.typestore()
    with McapRecorder(path) as rec:
        for i in range(3):
            stamp = (i + 1) * 10**8
            labels = np.zeros(grid.dims, np.uint8)
            labels[:50] = 7
            msg = occupancy_msg(
                RosbagsTypes(store), encode_labels(labels, grid, 24), stamp_ns=stamp, frame_id="cav_1/lidar", agent_id=1
            )
            raw = store.serialize_cdr(msg, "co3sop_msgs/msg/SemanticOccupancy")
            rec.write("/cav_1/ground_truth/occupancy_50m", "co3sop_msgs/msg/SemanticOccupancy", raw, stamp)
            rec.write(
                "/ego/occupancy",
                "co3sop_msgs/msg/SemanticOccupancy",
                raw[: len(raw) // 2] if i == malformed_at else raw,
                stamp,
            )
    return path


def test_score_explains_a_malformed_message_and_damaged_recordings(tmp_path):
    good = tool("score", str(_recording(tmp_path / "good.mcap", None)), "--pictures", "0")
    assert good.returncode == 0 and "3 predicted" in good.stdout, good.stderr
    bad = tool("score", str(_recording(tmp_path / "bad.mcap", 1)), "--pictures", "0")
    assert bad.returncode == 2 and "Traceback" not in bad.stderr, bad.stderr
    assert "bad.mcap: /ego/occupancy at 200000000 ns: not a valid co3sop_msgs/msg/SemanticOccupancy" in bad.stderr
    data = (tmp_path / "good.mcap").read_bytes()
    for name, content in (
        ("random.mcap", np.random.default_rng(1).bytes(len(data))),
        (
            "corrupt.mcap",
            data[: (at := _first_chunk_data(data))] + bytes(b ^ 0xFF for b in data[at : at + 8]) + data[at + 8 :],
        ),
    ):
        (tmp_path / name).write_bytes(content)
        done = tool("score", str(tmp_path / name), "--pictures", "0")
        assert done.returncode == 2 and f"{name}: damaged or not a MCAP recording" in done.stderr, done.stderr
        assert "Traceback" not in done.stderr
        failed = tool("recover", str(tmp_path / name))
        assert failed.returncode in (0, 2) and "Traceback" not in failed.stderr, failed.stderr
        assert not list(tmp_path.glob(".*.recovering")), "recover left its temporary file behind"


def test_generate_shards_are_disjoint_parts_of_one_dataset(tmp_path):
    """`generate --shard I/N` on N machines: each writes its share, the shares are disjoint and together the dataset."""
    from co3sop_nodes.sim.generation import scenario_name

    common = [
        "--splits",
        "train=2",
        "test=1",
        "--frames",
        "1",
        "--cavs",
        "1",
        "--image-size",
        "32x24",
        "--lidar-steps",
        "64",
        "--vehicles",
        "2",
        "--workers",
        "1",
        "--seed",
        "5",
    ]
    written = {}
    for shard in ("1/2", "2/2"):
        done = tool("generate", "--out", str(tmp_path / shard.replace("/", "of")), *common, "--shard", shard)
        assert done.returncode == 0, done.stderr
        written[shard] = {
            (split.name, s.name)
            for split in (tmp_path / shard.replace("/", "of")).iterdir()
            if split.name in ("train", "test")
            for s in split.iterdir()
        }
    assert written["1/2"] and written["2/2"] and written["1/2"].isdisjoint(written["2/2"])
    assert written["1/2"] | written["2/2"] == {
        ("train", scenario_name("train", 0, 5)),
        ("train", scenario_name("train", 1, 5)),
        ("test", scenario_name("test", 0, 5)),
    }
    for bad in ("3/2", "0/2", "half"):
        done = tool("generate", "--out", str(tmp_path / "bad"), *common, "--shard", bad)
        assert done.returncode == 2 and f"--shard {bad!r}" in done.stderr and "Traceback" not in done.stderr


def test_generate_gives_the_same_bytes_whatever_its_workers(tmp_path):
    """Workers beyond the scenarios become each scenario's threads: one scenario on 1 and on 3 workers, same files."""
    common = ["--splits", "test=1", "--frames", "2", "--cavs", "2", "--image-size", "64x48", "--lidar-steps", "128"]
    trees = []
    for workers in ("1", "3"):
        out = tmp_path / f"workers{workers}"
        done = tool("generate", "--out", str(out), *common, "--vehicles", "4", "--seed", "9", "--workers", workers)
        assert done.returncode == 0, done.stderr
        trees.append({p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()})
    assert trees[0].keys() == trees[1].keys() and len(trees[0]) > 10
    assert [k for k in trees[0] if trees[0][k] != trees[1][k]] == []
