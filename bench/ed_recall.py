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
ED tag-intersection recall and precision of a recorded run against the simulator's truth.

Reads a kept bench case (``run/run.mcap`` of ``mlv-ros run --dicom`` and ``study/`` with
``groundtruth.json``), builds each ED mask as the tag detector node does
(:class:`StreamingMasker`) and detects the ED intersections as its :class:`SliceTracker` does.
The truth is the simulator's undeformed SPAMM grid (``tag_pattern``: tag planes ⟂ the image
through its centre at ``tag_angle_deg``, period ``tag_spacing_mm``) intersected with the true ED
myocardium (``groundtruth.npz`` ``ed_masks``). A detection is right when it lies within
``--tol`` tag periods of a true intersection.

    python bench/ed_recall.py CASE_DIR [CASE_DIR ...] [--tol 0.2] [--per-slice]

Prints one JSON line per case: true intersections in the wall, detections, recall (true ones
found), precision (detections that are true ones), per view; with ``--per-slice`` also per slice.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mlv_ros.core.io.groundtruth import load_groundtruth  # noqa: E402, I100
from mlv_ros.core.registration.streaming import StreamingMasker  # noqa: E402
from mlv_ros.core.sim.imaging import plane_centre  # noqa: E402
from mlv_ros.core.tags import SliceTracker  # noqa: E402
from retrack import recorded  # noqa: E402


def true_intersections(
    geom, shape, spacing_mm: float, angle_deg: float, mask: np.ndarray
) -> np.ndarray:
    """Pixel (row, col) of the simulator's ED tag intersections inside ``mask``, (N, 2)."""
    c0 = plane_centre(geom, shape)
    ca, sa = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    u = ca * geom.row_direction + sa * geom.column_direction
    v = -sa * geom.row_direction + ca * geom.column_direction
    # (a, b) = A @ (r, c) + b0: linear in the pixel index.
    p0 = geom.pixel_to_patient(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))
    dr, dc = p0[1] - p0[0], p0[2] - p0[0]
    a_mat = np.array([[dr @ u, dc @ u], [dr @ v, dc @ v]])
    off = np.array([(p0[0] - c0) @ u, (p0[0] - c0) @ v])
    n = (
        int(np.ceil(np.hypot(*shape) * max(geom.row_spacing, geom.column_spacing) / spacing_mm))
        + 2
    )
    i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing='ij')
    ab = spacing_mm * np.stack([i.ravel(), j.ravel()], -1).astype(float)
    rc = np.linalg.solve(a_mat, (ab - off).T).T
    q = np.rint(rc).astype(int)
    ok = (q[:, 0] >= 0) & (q[:, 0] < shape[0]) & (q[:, 1] >= 0) & (q[:, 1] < shape[1])
    rc, q = rc[ok], q[ok]
    return rc[mask[q[:, 0], q[:, 1]]]


def case_recall(case: Path, tol: float = 0.2, per_slice: bool = False, **tracker_kwargs) -> dict:
    frames, _, _ = recorded(case / 'run' / 'run.mcap')
    gt = load_groundtruth(case / 'study')
    spacing_mm = float(gt.meta['protocol']['tag_spacing_mm'])
    angle = float(gt.meta['protocol']['tag_angle_deg'])
    masker = StreamingMasker()
    for f in frames:
        masker.observe_geometry(f)
    keys = list(gt.geometries)
    ipps = np.array([gt.geometries[k].image_position for k in keys])
    out, rows = {}, []
    for f in frames:
        if f.phase_index != 0:
            continue
        mask, _ = masker.ed_mask(f)
        pts = SliceTracker(f.geometry, **tracker_kwargs).update(f, mask=mask)
        k = keys[int(np.argmin(np.linalg.norm(ipps - f.geometry.image_position, axis=1)))]
        truth = true_intersections(
            gt.geometries[k], f.image.shape, spacing_mm, angle, gt.ed_masks[k]
        )
        period = spacing_mm / f.geometry.row_spacing
        det = np.asarray(pts.pixel_rc, float).reshape(-1, 2)
        found = right = 0
        if len(truth) and len(det):
            d_t, _ = cKDTree(det).query(truth)
            d_d, _ = cKDTree(truth).query(det)
            found, right = int(np.sum(d_t <= tol * period)), int(np.sum(d_d <= tol * period))
        view = 'SA' if f.view == 0 else 'LA'
        s = out.setdefault(view, {'truth': 0, 'detected': 0, 'found': 0, 'right': 0})
        s['truth'] += len(truth)
        s['detected'] += len(det)
        s['found'] += found
        s['right'] += right
        rows.append(
            {
                'view': view,
                'slice': int(f.slice_index),
                'truth': len(truth),
                'detected': len(det),
                'found': found,
                'right': right,
                'status': pts.status[:80],
            }
        )
    for s in out.values():
        s['recall'] = round(s['found'] / max(s['truth'], 1), 3)
        s['precision'] = round(s['right'] / max(s['detected'], 1), 3)
    res = {'case': case.name, **out}
    if per_slice:
        res['slices'] = rows
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('cases', nargs='+', type=Path)
    ap.add_argument(
        '--tol', type=float, default=0.2, help='match radius, tag periods (default 0.2)'
    )
    ap.add_argument('--per-slice', action='store_true')
    args = ap.parse_args()
    for case in args.cases:
        print(json.dumps(case_recall(case, args.tol, args.per_slice)), flush=True)


if __name__ == '__main__':
    sys.exit(main())
