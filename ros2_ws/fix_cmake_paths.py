"""Point the ROS wheels' exported CMake files at this interpreter's include folders.

The PyPI ROS 2 Jazzy wheels were built in a manylinux container; their exported
CMake targets name that container's Python and NumPy include folders, which do
not exist here, so `colcon build` of any message package fails with
'Imported target ... includes non-existent path'. Rewriting them is idempotent:
a second run finds nothing to change.
"""

from __future__ import annotations

import pathlib
import sys
import sysconfig

import numpy

# The wheels for this interpreter's version were built with the container's Python of that version.
_V = f"{sys.version_info.major}.{sys.version_info.minor}"
_BUILD_PREFIX = f"/opt/python/cp{_V.replace('.', '')}-cp{_V.replace('.', '')}"
BUILD_PYTHON_INCLUDE = f"{_BUILD_PREFIX}/include/python{_V}"
BUILD_NUMPY_INCLUDE = f"{_BUILD_PREFIX}/lib/python{_V}/site-packages/numpy/_core/include"


def main(prefix: str) -> int:
    replacements = {
        # The NumPy path contains the Python one's prefix: replace it first.
        BUILD_NUMPY_INCLUDE: numpy.get_include(),
        BUILD_PYTHON_INCLUDE: sysconfig.get_paths()["include"],
    }
    changed = 0
    for path in pathlib.Path(prefix, "share").rglob("*.cmake"):
        text = path.read_text(encoding="utf-8", errors="surrogateescape")
        new = text
        for old, repl in replacements.items():
            new = new.replace(old, repl)
        if new != text:
            path.write_text(new, encoding="utf-8", errors="surrogateescape")
            changed += 1
    print(f"fix_cmake_paths: {changed} CMake file(s) rewritten under {prefix}/share")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else sys.prefix))
