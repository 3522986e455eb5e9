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
Write the whole bad-input corpus to disk: ``python test/make_bad_input_corpus.py OUT_DIR``.

``OUT_DIR/dicom/``     the DICOM cases beside a small valid study (``read_dicom_dir`` or
                       ``mlv-ros run --dicom OUT_DIR/dicom`` on it: every bad file reported, the
                       study still loads);
``OUT_DIR/messages.mcap``  the valid study's frames interleaved with every bad message, as a
                       rosbag2-style MCAP (``ros2 run mlv_ros replay --ros-args -p path:=...`` or
                       ``mlv-ros run --bag``: every bad message reported, every phase solved);
``OUT_DIR/manifest.json``  one entry per case: name, kind, category, where it is and what the
                       report about it must say.

The tests build the same cases in memory (``test_dicom_corpus.py``, ``test_message_corpus.py``);
this script is for looking at them, replaying them and fuzzing from them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys

sys.path.insert(0, str(Path(__file__).resolve().parent))

from corpus.dicom_cases import write_dicom_corpus  # noqa: E402
from corpus.message_cases import message_cases  # noqa: E402


def interleave(valid: list, cases: list) -> list:
    """
    Return (topic, msg) pairs in sending order.

    (topic, msg) in sending order: each stand-in replaces its valid frame, each derived case
    follows its source frame, and the other cases come after the study.
    """
    from corpus.message_cases import frames_with_cases
    from mlv_ros import qos

    out = []
    for frame, derived in frames_with_cases(valid, cases):
        out.append((qos.FRAMES, frame))
        out += [(c.topic, c.msg) for c in derived]
    placed = {id(c) for c in cases if c.replaces is not None or c.after is not None}
    out += [(c.topic, c.msg) for c in cases if id(c) not in placed]
    return out


def write_corpus(out_dir: Path, num_phases: int = 3, size: int = 48) -> dict:
    """Write the corpus into ``out_dir`` (created; must hold none yet); return the manifest."""
    from mlv_ros import bagio, conversions, qos
    from mlv_ros.core.io import write_study_dicom
    from mlv_ros.core.sim import simulate_study
    from mlv_ros.nodes.frame_source import count_slices, order_frames
    from rclpy.serialization import serialize_message

    out_dir = Path(out_dir)
    if (out_dir / 'manifest.json').exists():
        raise FileExistsError(f'{out_dir} already holds a corpus')
    study = simulate_study(
        'normal', snr=20.0, size=size, num_phases=num_phases, subplanes=1, seed=2
    )
    good = write_study_dicom(study, out_dir / 'dicom' / 'valid')
    dicom = write_dicom_corpus(out_dir / 'dicom', good)

    frames = order_frames(count_slices(list(study.frames)), 'slice_major')
    valid = [conversions.frame_to_msg(f, stamp=1.0 + i) for i, f in enumerate(frames)]
    messages = message_cases(valid)
    writer = bagio.BagWriter(out_dir / 'messages.mcap')
    for topic in sorted({c.topic for c in messages} | {qos.FRAMES}):
        writer.add_topic(topic, qos.TOPIC_TYPES[topic], [qos.qos_dict(qos.topic_qos(topic))])
    for i, (topic, msg) in enumerate(interleave(valid, messages)):
        writer.write(topic, serialize_message(msg), 1_000_000_000 + i * 1000)
    writer.close()

    manifest = {
        'valid_study': {
            'dicom_files': len(good),
            'frames': len(valid),
            'num_phases': num_phases,
            'size': size,
        },
        'cases': [
            {
                'name': c.name,
                'kind': 'dicom',
                'category': c.category,
                'outcome': c.outcome,
                'files': [str(p.relative_to(out_dir)) for p in c.files],
                'expect': c.expect,
            }
            for c in dicom
        ]
        + [
            {
                'name': c.name,
                'kind': 'message',
                'category': c.category,
                'topic': c.topic,
                'stamp': c.stamp,
                'node': c.node,
                'expect': c.expect,
                'replaces_valid_frame': c.replaces is not None,
            }
            for c in messages
        ],
    }
    manifest['count'] = len(manifest['cases'])
    (out_dir / 'manifest.json').write_text(json.dumps(manifest, indent=1))
    return manifest


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('out_dir', type=Path)
    args = parser.parse_args(argv)
    manifest = write_corpus(args.out_dir)
    kinds = {}
    for c in manifest['cases']:
        kinds[c['kind']] = kinds.get(c['kind'], 0) + 1
    print(json.dumps({'out_dir': str(args.out_dir), 'cases': manifest['count'], 'by_kind': kinds}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
