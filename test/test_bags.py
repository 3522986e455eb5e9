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
The sample acquisition in bags/: small, independently readable, the frames of its DICOM source.

The sample acquisition in bags/: small, readable by an independent reader, and holding exactly
the frames its DICOM source gives (so replaying it drives the graph exactly like the DICOM).
"""

import importlib.util
from pathlib import Path

from mlv_ros import qos
from mlv_ros.nodes.frame_source import read_bag_frames
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores

BAGS = Path(__file__).resolve().parents[1] / 'bags'
SAMPLE = BAGS / 'normal_sample.mcap'


def load_maker():
    spec = importlib.util.spec_from_file_location('make_sample', BAGS / 'make_sample.py')
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_sample_bag_is_small_and_rosbags_reads_it():
    assert SAMPLE.stat().st_size <= 10 * 1024 * 1024
    with AnyReader([SAMPLE], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        assert [c.topic for c in reader.connections] == [qos.FRAMES]
        n = sum(1 for _ in reader.messages())
    assert n == 11 * 16


@pytest.mark.slow
def test_sample_bag_holds_exactly_the_frames_of_its_dicom_source(tmp_path):
    maker = load_maker()
    from_dicom = maker.sample_frames(maker.sample_dicom(tmp_path / 'dicom'))
    from_bag = read_bag_frames(SAMPLE)
    assert len(from_bag) == len(from_dicom) == 176
    for a, b in zip(from_dicom, from_bag):
        assert (a.view, a.slice_index, a.phase_index, a.num_sa_slices, a.num_la_slices) == (
            b.view,
            b.slice_index,
            b.phase_index,
            b.num_sa_slices,
            b.num_la_slices,
        )
        assert a.image.dtype == b.image.dtype and np.array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.geometry.image_position, b.geometry.image_position)
        assert a.trigger_time == b.trigger_time
