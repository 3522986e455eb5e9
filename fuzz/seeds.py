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
Seed inputs for the fuzz targets: valid DICOM files and valid serialised messages.

Written fresh by ``fuzz/run.py`` (never committed): whatever the writers and converters produce
today is what the fuzzer starts from.
"""

from __future__ import annotations

from pathlib import Path

from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.types import Frame, ModelState, TagPointSet, VIEW_LA, VIEW_SA
import numpy as np

#: Message types of fuzz_messages.py, in the order of its selector byte (first input byte).
MESSAGE_TYPES = (
    'TaggedFrame',
    'TagPoints',
    'ModelState',
    'MotionMetrics',
    'SliceGeometry',
    'Image',
    'PointCloud2',
)


def _small_frame(rows: int, cols: int, image_dtype=np.float32) -> Frame:
    rng = np.random.default_rng(rows * 100 + cols)
    image = rng.random((rows, cols))
    image = (
        (image * 1000).astype(np.uint16) if image_dtype == np.uint16 else image.astype(np.float32)
    )
    geom = SliceGeometry(
        np.array([-20.0, 10.0, 5.0]),
        np.array([1.0, 0.0, 0.0]),
        np.array([0.0, 0.6, 0.8]),
        1.25,
        1.25,
        8.0,
    )
    return Frame(
        image=image,
        geometry=geom,
        view=VIEW_SA,
        slice_index=1,
        phase_index=2,
        num_phases=5,
        trigger_time=0.2,
        cycle_duration=1.0,
        series_uid='1.2.3.4',
        num_sa_slices=3,
        num_la_slices=1,
    )


def dicom_seeds(out_dir: Path) -> list[Path]:
    """Write a few valid files: simulated SA and LA images (32²), tiny float and uint16 frames."""
    from mlv_ros.core.io.dicom import frame_to_dataset, write_study_dicom
    from mlv_ros.core.sim import simulate_study

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    study = simulate_study('normal', snr=20.0, size=32, num_phases=2, subplanes=1, seed=0)
    written = write_study_dicom(study, out / 'study')
    paths = []
    for i, p in enumerate([written[0], written[-1]]):  # one SA, one LA
        q = out / f'sim_{i}.dcm'
        q.write_bytes(p.read_bytes())
        paths.append(q)
    for rows, cols, dtype in ((4, 4, np.float32), (3, 5, np.uint16)):
        q = out / f'tiny_{rows}x{cols}_{np.dtype(dtype).name}.dcm'
        frame_to_dataset(_small_frame(rows, cols, dtype)).save_as(q, enforce_file_format=True)
        paths.append(q)
    for p in (out / 'study').rglob('*'):
        if p.is_file():
            p.unlink()
    return paths


def message_seeds(out_dir: Path) -> list[Path]:
    """Write one valid serialised message per type, prefixed with its type index (the selector)."""
    from mlv_ros import conversions
    from rclpy.serialization import serialize_message

    frame = _small_frame(4, 6)
    points = TagPointSet(
        view=VIEW_LA,
        slice_index=0,
        phase_index=1,
        num_phases=5,
        geometry=frame.geometry,
        pixel_rc=np.array([[1.0, 2.0], [3.5, 4.5]]),
        position=np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]),
        track_id=np.array([7, 9]),
        confidence=np.array([0.5, 1.0]),
    )
    metrics = {
        'phase_index': 1,
        'num_phases': 5,
        **{n: np.arange(3.0) for n in conversions.METRIC_LEVEL_FIELDS},
        **{n: np.zeros(17) for n in conversions.METRIC_SEGMENT_FIELDS},
        **{n: 0.5 for n in conversions.METRIC_SCALAR_FIELDS},
    }
    msgs = {
        'TaggedFrame': conversions.frame_to_msg(frame, stamp=1.5),
        'TagPoints': conversions.tagpoints_to_msg(points, stamp=1.5),
        'ModelState': conversions.model_state_to_msg(
            ModelState(phase_index=1, num_phases=5), stamp=1.5
        ),
        'MotionMetrics': conversions.metrics_to_msg(metrics, stamp=1.5),
        'SliceGeometry': conversions.geometry_to_msg(frame.geometry),
        'Image': conversions.image_to_msg(frame.image),
        'PointCloud2': conversions.cloud_to_msg(
            {'x': np.arange(3.0), 'y': np.ones(3), 'z': np.zeros(3)}
        ),
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for index, name in enumerate(MESSAGE_TYPES):
        p = out / f'{index:02d}_{name}.bin'
        p.write_bytes(bytes([index]) + serialize_message(msgs[name]))
        paths.append(p)
    return paths
