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
atheris target: arbitrary bytes deserialised as each of our message types, then decoded.

The first byte picks the type; the rest goes through ``rclpy.serialization.deserialize_message``
and then the matching ``mlv_ros.conversions.msg_to_*``. Allowed outcomes: a message that decodes,
rclpy's ``RMWError`` for bytes that are not valid CDR of that type, or ``ValueError`` (and its
subclasses) from the decoder, as documented in ``conversions``. Any other exception is a finding.

    python fuzz/fuzz_messages.py [libFuzzer flags] CORPUS_DIR [SEED_DIR ...]   (see fuzz/README.md)
"""

import sys

import atheris

with atheris.instrument_imports(include=['mlv_ros']):
    from mlv_msgs.msg import ModelState, MotionMetrics, SliceGeometry, TaggedFrame, TagPoints
    from mlv_ros import conversions
    from rclpy._rclpy_pybind11 import RMWError
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image, PointCloud2

from seeds import MESSAGE_TYPES  # noqa: E402  (the selector order, shared with the seeds)

#: Message type name → (type, decoder).
TARGETS = {
    'TaggedFrame': (TaggedFrame, conversions.msg_to_frame),
    'TagPoints': (TagPoints, conversions.msg_to_tagpoints),
    'ModelState': (ModelState, conversions.msg_to_model_state),
    'MotionMetrics': (MotionMetrics, conversions.msg_to_metrics),
    'SliceGeometry': (SliceGeometry, conversions.msg_to_geometry),
    'Image': (Image, conversions.msg_to_image),
    'PointCloud2': (PointCloud2, lambda m: conversions.msg_to_cloud(m, required=('x', 'y', 'z'))),
}
if set(TARGETS) != set(MESSAGE_TYPES):
    raise RuntimeError(f'fuzz_messages.TARGETS {sorted(TARGETS)} and seeds.MESSAGE_TYPES disagree')
_ORDER = [TARGETS[name] for name in MESSAGE_TYPES]


def TestOneInput(data: bytes) -> None:
    if not data:
        return
    msg_type, decode = _ORDER[data[0] % len(_ORDER)]
    try:
        msg = deserialize_message(data[1:], msg_type)
    except RMWError:
        return  # not valid CDR for this type: rclpy's documented failure
    try:
        decode(msg)
    except ValueError:
        return  # the converters' documented failure


def main() -> None:
    atheris.Setup(sys.argv, TestOneInput)
    atheris.Fuzz()


if __name__ == '__main__':
    main()
