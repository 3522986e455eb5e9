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
Tag detection and tracking for 1-1 SPAMM tagged MRI (pure numpy/scipy/OpenCV; no ROS).

Public API
----------
``detect_intersections(image, mask=None, spacing_px=None, angles=None, *, ...) -> Detection``
    Stateless. Estimates the tag spacing and the two tag directions from the image spectrum
    (unless given), filters with a complex Gabor bank (3 orientations × 3 spacings per direction,
    zero-mean kernels, FFT), takes per pixel the strongest response, and returns the points where
    both directions' phases are ≡ π (dark tag centres), refined to sub-pixel accuracy by Newton's
    method on the two wrapped phases and then with kernels tuned to each point's local wave
    vectors (the bank's quantised tuning biases points next to the wall's border), with a
    confidence (response over local contrast) and grid labels (k1, k2). With a mask, the image is
    zero-meaned locally inside it and zeroed outside first (removes the blood-pool edge bias). Bad
    input (constant image, NaN pixels, no tags, < 16×16 px …) gives an empty :class:`Detection`
    whose ``reason`` says why; it never raises for image content.

``SliceTracker(geometry=None, *, spacing_px=None, angles=None, max_gap=1, gate=0.4, ...)``
    Stateful, one per (view, slice). ``tracker.update(frame, mask=None) -> TagPointSet`` once per
    phase in phase order (phase 0 = ED starts a cine and assigns track ids; pass the ED
    myocardium mask there: without it every tagged tissue, static chest wall included, is
    tracked). Later phases: prediction by the previous displacement, the ED mask carried along
    by a TPS through the tracks, detection near the prediction, TPS-RPM matching, then a second
    detection with the mask carried through the matched points that must confirm each match;
    undetected points are dropped (after ``max_gap`` coasting phases), never invented; a slice
    left with fewer than 4 tracks ends them and takes its tracks up again only where its ED grid
    is seen again (``REACQUIRE_SHARE`` of them at once). Points carry
    patient coordinates (mm) from the slice geometry. Never raises: problems come back as an empty
    (or partial) set with ``status`` set.

``LineTracker(geometry=None, *, spacing_px, angle, ...)`` and ``detect_line_points(...)``
    Single-line SPAMM (one family of parallel lines, no intersections): points about one
    period apart along each line, tracked by the family's Gabor phase along the line normal
    only (:mod:`mlv_ros.core.tags.lines`); the TagPointSet carries each point's line normal
    (``line_normal``), the one direction it measures. ``LineSliceTracker(geometry)`` tracks a
    slice of a single-line study (``Frame.tag_lines``): each family's period and angle
    estimated at ED inside the myocardium, a line pair's two families in one set, the second
    series' breath-hold shift from the first estimated on the shared anatomy and corrected
    (``estimate_pair_shift``, :mod:`mlv_ros.core.tags.line_pair`).

``harp_track(images, start_rc, params) -> HarpTrack``
    HARP baseline (Osman et al. 1999): band-pass one spectral peak per direction, harmonic
    phase, phase-constancy Newton tracking; for comparison in ``bench/tags.py``.

``tps_rpm(source, target, ...) -> RPMResult`` and ``ThinPlateSpline``
    Chui & Rangarajan (2003) robust point matching with outlier row/column and Sinkhorn
    normalisation; usable on its own.

``estimate_tag_parameters(image, mask=None) -> TagParameters``
    Spectral estimate of the tag spacing (px) and wave-vector angles (rad).

Conventions
-----------
Pixel coordinates are (row, col). A tag direction is the angle θ of its wave vector (normal to
its tag lines) from the column axis toward the row axis, in [0, π); unit wave vector
(sin θ, cos θ) in (row, col) order. Spacing = distance between tag lines, px.

Examples
--------
>>> from mlv_ros.core.tags import detect_intersections, SliceTracker
>>> det = detect_intersections(frame.image, mask=myocardium)
>>> det.pixel_rc, det.labels, det.confidence, det.reason
>>> tracker = SliceTracker(frame.geometry)
>>> points = tracker.update(frame, mask=myocardium)    # ED
>>> points = tracker.update(next_frame)                 # phase 1, 2, …

References
----------
Chen, T., Wang, X., Chung, S., Metaxas, D., Axel, L. IEEE TMI 29(1):1–11, 2010.
Chui, H., Rangarajan, A. Computer Vision and Image Understanding 89:114–141, 2003.
Osman, N. F., Kerwin, W. S., McVeigh, E. R., Prince, J. L. Magn. Reson. Med. 42:1048–1060, 1999.

"""

from .gabor import (
    estimate_tag_parameters,
    gabor_filter_bank,
    GaborMaps,
    kernel_bank,
    TagInputError,
    TagParameters,
)
from .harp import harmonic_phase, harp_track, HarpTrack
from .intersections import (
    detect_intersections,
    Detection,
    estimate_grid,
    grid_coherence,
    grid_labels,
)
from .line_pair import estimate_pair_shift, PairShift
from .lines import (
    detect_line_points,
    estimate_line_family,
    line_parameters,
    LinePoints,
    LineSliceTracker,
    LineTracker,
)
from .rpm import RPMResult, ThinPlateSpline, tps_rpm
from .tracker import SliceTracker

__all__ = [
    'Detection',
    'GaborMaps',
    'HarpTrack',
    'LinePoints',
    'LineSliceTracker',
    'LineTracker',
    'PairShift',
    'RPMResult',
    'SliceTracker',
    'TagInputError',
    'TagParameters',
    'ThinPlateSpline',
    'detect_intersections',
    'detect_line_points',
    'estimate_line_family',
    'estimate_pair_shift',
    'estimate_grid',
    'estimate_tag_parameters',
    'grid_coherence',
    'gabor_filter_bank',
    'grid_labels',
    'harmonic_phase',
    'harp_track',
    'kernel_bank',
    'line_parameters',
    'tps_rpm',
]
