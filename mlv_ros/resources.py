# Copyright 2026 The mlv_ros authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

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
