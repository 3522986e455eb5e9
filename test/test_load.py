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
Load: a whole study published at once into the graph plus the recorder, no frame lost.

Load: a whole study published at once, as fast as possible, slice-major, into the graph plus
the recorder — no frame may be lost anywhere (published = received by the tag detector = tag
sets out = recorded), and every phase must be solved and analysed.
"""

import json

from graphkit import run_load
from mlv_ros.core.sim import simulate_study
import pytest

pytestmark = pytest.mark.slow  # a graph run: scheduled first (conftest)

PHASES = 10


def test_whole_study_burst_loses_nothing(tmp_path):
    frames = list(simulate_study('normal', snr=20, size=128, num_phases=PHASES).frames)
    report = run_load(frames, tmp_path, order='slice_major', timeout=240, stall_s=60)
    print('\nload:', json.dumps(report.as_dict()))
    assert report.published == len(frames) == 11 * PHASES
    assert report.detector_received == report.published, report
    assert report.tag_sets == report.published, report
    assert report.recorded_frames == report.published, report
    assert report.recorded_tag_sets == report.published, report
    assert report.frames_lost == 0
    assert report.phases_solved == report.phases_analysed == PHASES, report
