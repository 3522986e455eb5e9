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

"""Absurd declared sizes are refused before anything of that size is allocated."""

import resource

from conftest import spin_until
from mlv_msgs.msg import TaggedFrame, TagPoints
from mlv_ros import conversions, qos
from mlv_ros.core.io.dicom import read_dicom_dir, write_study_dicom
from mlv_ros.core.sim import simulate_study
from mlv_ros.nodes.tag_detector import TagDetector
import pydicom
from rclpy.parameter import Parameter


def test_dicom_declaring_a_65535_square_image_is_reported_not_loaded(tmp_path):
    study = simulate_study('normal', quick=True, num_phases=2)
    files = write_study_dicom(study, tmp_path)
    ds = pydicom.dcmread(files[0])
    ds.Rows = ds.Columns = 65535  # 8.6 GB of pixels declared, 32 KB present
    ds.save_as(files[0])
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    frames, problems = read_dicom_dir(tmp_path)
    assert len(frames) == len(files) - 1
    assert len(problems) == 1 and str(files[0].name) in str(problems[0][0])
    assert (
        resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 500 * 1024
    )  # KiB: < 500 MB grew


def test_tag_detector_refuses_oversized_frames_before_converting(ros_context, executor):
    import rclpy

    node = TagDetector(
        context=ros_context, parameter_overrides=[Parameter('max_pixels', value=64 * 64)]
    )
    got = []
    sink = rclpy.create_node('sink', context=ros_context)
    sink.create_subscription(TagPoints, qos.TAG_POINTS, got.append, qos.stream_qos())
    pub = sink.create_publisher(TaggedFrame, qos.FRAMES, qos.topic_qos(qos.FRAMES))
    executor.add_node(node)
    executor.add_node(sink)
    frame = simulate_study('normal', quick=True, num_phases=2).frames[0]
    assert spin_until(executor, lambda: pub.get_subscription_count() >= 1, 20)
    pub.publish(conversions.frame_to_msg(frame))  # 128 × 128 > 64 × 64
    assert spin_until(executor, lambda: len(got) == 1, 20)
    assert got[0].status == 'image too large' and len(got[0].track_id) == 0
    assert node.published == 1 and not node.trackers  # nothing was tracked or allocated for it
