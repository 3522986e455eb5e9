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
A built-in analytic test pattern: a short-axis stack of rotating 1-1 SPAMM grid images.

The grid rotates rigidly over the cycle. Used for smoke tests of the graph before a full phantom is
needed; the realistic simulator is :func:`mlv_ros.core.sim.simulate_study`.
"""

from __future__ import annotations

from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.types import Frame, VIEW_SA
import numpy as np


def pattern_frames(
    num_slices: int = 2,
    num_phases: int = 3,
    size: int = 64,
    spacing_mm: float = 7.0,
    pixel_mm: float = 1.3,
    max_rotation_deg: float = 10.0,
) -> list[Frame]:
    """
    Return the frames (slice-major) of a tag grid rotating about the image centre.

    Rotation up to ``max_rotation_deg``, uint16 pixels; slices 8 mm apart along patient z.
    """
    if num_slices < 1 or num_phases < 1 or size < 8:
        raise ValueError('pattern needs ≥ 1 slice, ≥ 1 phase and size ≥ 8 pixels')
    k = 2 * np.pi / spacing_mm
    rr, cc = np.mgrid[0:size, 0:size].astype(np.float64)
    y, x = (rr - size / 2) * pixel_mm, (cc - size / 2) * pixel_mm
    frames = []
    for s in range(num_slices):
        geom = SliceGeometry(
            np.array([-size / 2 * pixel_mm, -size / 2 * pixel_mm, -8.0 * s]),
            np.array([1.0, 0, 0]),
            np.array([0, 1.0, 0]),
            pixel_mm,
            pixel_mm,
            6.0,
        )
        for p in range(num_phases):
            a = np.deg2rad(max_rotation_deg) * np.sin(np.pi * p / max(num_phases, 1))
            u, v = np.cos(a) * x + np.sin(a) * y, -np.sin(a) * x + np.cos(a) * y  # material coords
            img = np.sin(k * u / 2) ** 2 * np.sin(k * v / 2) ** 2
            frames.append(
                Frame(
                    image=(img * 3000 + 200).astype(np.uint16),
                    geometry=geom,
                    view=VIEW_SA,
                    slice_index=s,
                    phase_index=p,
                    num_phases=num_phases,
                    trigger_time=0.04 * p,
                    cycle_duration=0.04 * num_phases,
                    series_uid=f'pattern.{s}',
                    num_sa_slices=num_slices,
                    num_la_slices=0,
                )
            )
    return frames
