"""Install kvark_ros with pip (``pip install -e .[sim,test]``) or colcon (ament_python)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "kvark_ros"


def _tree(folder: str) -> list[tuple[str, list[str]]]:
    """data_files entries that install ``folder`` under share/kvark_ros, keeping sub-folders."""
    entries: dict[str, list[str]] = {}
    for path in glob(f"{folder}/**/*", recursive=True):
        if "." in path.rsplit("/", 1)[-1] and "__pycache__" not in path:
            target = f"share/{PACKAGE}/" + path.rsplit("/", 1)[0]
            entries.setdefault(target, []).append(path)
    return sorted(entries.items())


setup(
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        *_tree("launch"),
        *_tree("config"),
        *_tree("models"),
        *_tree("rviz"),
        *_tree("plotjuggler"),
    ],
)
