from glob import glob

from setuptools import find_packages, setup

PACKAGE = "co3sop_nodes"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "tests"]),
    package_data={PACKAGE: ["kernels/*.c", "kernels/*.h"]},  # C kernels, compiled on first use (co3sop_nodes.kernels)
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "rosdep.yaml"]),
        (f"share/{PACKAGE}/config", glob("config/*")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/checkpoints", glob("checkpoints/*")),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # `colcon test` runs pytest (setup.cfg says where the tests are)
    zip_safe=False,  # the C sources are read from the installed package
    maintainer="Co3SOP ROS 2 developers",
    maintainer_email="dev@co3sop.local",
    description="Co3SOP collaborative 3D semantic occupancy prediction on ROS 2",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            f"monitor = {PACKAGE}.ros.monitor:main",
            f"sample_stream = {PACKAGE}.ros.sample_stream:main",
            f"player = {PACKAGE}.ros.player:main",
            f"vehicle = {PACKAGE}.ros.vehicle:main",
            f"ego = {PACKAGE}.ros.ego:main",
            f"recorder = {PACKAGE}.ros.recorder:main",
            f"demo = {PACKAGE}.cli.demo:entry",
            f"score = {PACKAGE}.cli.score:entry",
            f"recover = {PACKAGE}.cli.recover:entry",
            f"generate = {PACKAGE}.cli.generate:entry",
            f"convert = {PACKAGE}.cli.convert:entry",
            f"info = {PACKAGE}.cli.info:entry",
            f"calibrate = {PACKAGE}.cli.calibrate:entry",
            f"voxelize = {PACKAGE}.cli.voxelize:entry",
            f"train = {PACKAGE}.cli.train:entry",
            f"evaluate = {PACKAGE}.cli.evaluate:entry",
            f"report = {PACKAGE}.cli.report:entry",
        ],
    },
)
