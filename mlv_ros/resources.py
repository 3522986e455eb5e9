"""
Where the package's data files are.

``config/`` in a source checkout (editable install) or ``share/mlv_ros/config`` in an installed ROS
package (colcon).
"""

from __future__ import annotations

from pathlib import Path

_SOURCE_ROOT = Path(__file__).resolve().parents[1]


def config_dir() -> Path:
    """Directory holding ``graph.yaml`` and ``phantoms/*.yaml``."""
    local = _SOURCE_ROOT / 'config'
    if local.is_dir():
        return local
    from ament_index_python.packages import get_package_share_directory  # ROS install only

    return Path(get_package_share_directory('mlv_ros')) / 'config'


def config_file(*parts: str) -> Path:
    """Path of a file under :func:`config_dir`; raises ``FileNotFoundError`` naming it."""
    path = config_dir().joinpath(*parts)
    if not path.is_file():
        raise FileNotFoundError(f'config file not found: {path}')
    return path
