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
Readers and writers: DICOM tagged cine MR and simulator ground truth.

:mod:`.dicom` and :mod:`.groundtruth`. Pure Python + pydicom; no rclpy.

Public API
----------
write_study_dicom(study, out_dir, pixel_scale=1000, progress=None, *, bits_stored=16,
                  rescale=True, rescale_intercept=0.0, sa_series="per_slice",
                  instance_numbers="per_slice", file_names="ordered", names_seed=0) -> list[Path]
read_dicom_dir(path, max_pixels=DEFAULT_MAX_PIXELS, study=None) -> DicomReadResult
    (``frames, problems = read_dicom_dir(path)``; also ``.warnings``, ``.series``,
    ``.long_axis``, and the study selection: ``.study_uid``, ``.studies``, ``.choice``,
    ``.complete``, ``.left_out``, ``.not_used``; ``study`` = a StudyInstanceUID to load instead of
    the one with the most tagged cines; raises DicomReadError when nothing is usable or ``study``
    is absent)
WORKING_DTYPES
    The frames' pixel types (uint8/uint16 stored without a rescale, float32 otherwise), each
    publishable as a sensor_msgs/Image
write_groundtruth(study, out_dir, extra=None) -> (json_path, npz_path)
load_groundtruth(path) -> GroundTruth
motion_from_groundtruth(path) -> LVMotion (the exact motion, rebuilt from the JSON)
"""

from mlv_ros.core.io.dicom import (
    DicomReadError,
    DicomReadResult,
    estimate_long_axis,
    frame_to_dataset,
    LongAxisEstimate,
    read_dicom_dir,
    SeriesInfo,
    WORKING_DTYPES,
    write_study_dicom,
)
from mlv_ros.core.io.groundtruth import (
    GroundTruth,
    load_groundtruth,
    motion_from_groundtruth,
    write_groundtruth,
)

__all__ = [
    'DicomReadError',
    'DicomReadResult',
    'GroundTruth',
    'LongAxisEstimate',
    'SeriesInfo',
    'estimate_long_axis',
    'frame_to_dataset',
    'load_groundtruth',
    'motion_from_groundtruth',
    'read_dicom_dir',
    'write_groundtruth',
    'write_study_dicom',
    'WORKING_DTYPES',
]
