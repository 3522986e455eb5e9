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
``test/make_bad_input_corpus.py``: the whole bad-input corpus written to disk.

``test/make_bad_input_corpus.py`` writes the whole corpus (≥ 200 cases) to disk: DICOM files, a
replayable MCAP of the bad messages among a valid study, and a manifest — all readable by
independent tools (pydicom is not needed to check the files exist; rosbags reads the bag).
"""

import json

from graphkit import TOPIC_MSG
from make_bad_input_corpus import write_corpus
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader
from rosbags.highlevel.anyreader import AnyReaderError
from rosbags.typesys import get_typestore, Stores


def test_corpus_script_writes_every_case(tmp_path):
    manifest = write_corpus(tmp_path / 'corpus')
    cases = manifest['cases']
    assert manifest['count'] == len(cases) >= 200
    assert len({c['name'] for c in cases}) == len(cases)
    assert {c['kind'] for c in cases} == {'dicom', 'message'}
    for c in cases:
        if c['kind'] == 'dicom':
            assert c['files'] and all((tmp_path / 'corpus' / f).is_file() for f in c['files']), c[
                'name'
            ]
    assert json.loads((tmp_path / 'corpus' / 'manifest.json').read_text())['count'] == len(cases)

    # The bag: every message case plus every valid frame, none lost, readable by rosbags.
    messages = [c for c in cases if c['kind'] == 'message']
    bag = tmp_path / 'corpus' / 'messages.mcap'
    stamps = []
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, _t, raw in reader.messages():
            try:
                header = reader.deserialize(raw, conn.msgtype).header
            except AnyReaderError:
                # Known: rmw_fastrtps sizes a message with an empty float64[] as if the empty
                # sequence were 8-aligned and leaves those bytes at its end; rosbags accepts at
                # most 3 trailing bytes. rclpy reads it; only such messages may fail here.
                msg = deserialize_message(raw, TOPIC_MSG[conn.topic])
                assert any(len(getattr(msg, f)) == 0 for f in ('pixel_rc', 'position')), conn.topic
                header = msg.header
            stamps.append(f'{header.stamp.sec}.{header.stamp.nanosec:09d}')
    stand_ins = sum(c['replaces_valid_frame'] for c in messages)
    assert len(stamps) == manifest['valid_study']['frames'] - stand_ins + len(messages)
    assert {c['stamp'] for c in messages} <= set(stamps)
