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
Accuracy of a tracked run against analytic ground truth (simulator phantoms).

Every particle is a material point: its registered ED position ``X`` is taken as the material
coordinate, and its true position at phase t is ``motion.position(X, t)``. Twist and radius per
level are compared with the same analysis applied to the true positions, so both sides use one
definition.
"""

from __future__ import annotations

from mlv_ros.core.analysis import LVAnalyzer
from mlv_ros.core.analysis.frame import levels_outside, twist_extrapolation_bound
import numpy as np
from scipy.spatial import cKDTree


def evaluate_run(
    X_ed: np.ndarray, positions: dict, motion, analyzer: LVAnalyzer | None = None, sa_span=None
) -> dict:
    """
    Errors of tracked positions against the ground-truth motion.

    Parameters
    ----------
    X_ed : ndarray, shape (N, 3)
        Registered ED particles, mm.
    positions : dict int → ndarray (N, 3)
        Tracked positions per phase, mm.
    motion : LVMotion
        Ground truth (:func:`mlv_ros.core.sim.make_motion`).
    analyzer : LVAnalyzer, optional
        For per-level twist / radius errors.
    sa_span : (float, float), optional
        Lowest and highest SA slice as level positions (0 apex … 1 base): adds
        ``twist_error_measured_deg``, the twist error over the levels the SA stack spans (beyond
        it SA tags, the only ones that see circumferential motion, are absent and twist is
        extrapolated), and, when some level is extrapolated, ``twist_extrapolated_over_stated``:
        the largest ratio of an extrapolated level's twist error to the rate part of the
        uncertainty the run states for it
        (:func:`~mlv_ros.core.analysis.frame.twist_extrapolation_bound`; ≤ 1: within even the
        least the run states, whose sentence adds the study's own gradient noise).

    Returns
    -------
    dict
        ``per_phase``: list of {phase, median_mm, p95_mm, max_mm, rms_mm}; ``es``: the same at
        end-systole plus ``twist_error_deg`` (max over levels) and ``radius_error_mm`` when an
        analyzer is given; ``inside_myocardium``: fraction of ED particles inside the truth;
        ``coverage``: :func:`myocardium_coverage` (errors are measured on the particles, so a
        model that misses the base scores well on what it has: this says what it misses).

    """
    X = np.asarray(X_ed, dtype=np.float64)
    out = {
        'per_phase': [],
        'inside_myocardium': float(np.mean(motion.inside_myocardium(X))),
        'coverage': myocardium_coverage(X, motion),
    }
    for phase in sorted(positions):
        err = np.linalg.norm(np.asarray(positions[phase]) - motion.position(X, phase), axis=1)
        row = {
            'phase': int(phase),
            'median_mm': float(np.median(err)),
            'p95_mm': float(np.percentile(err, 95)),
            'max_mm': float(err.max()),
            'rms_mm': float(np.sqrt(np.mean(err**2))),
        }
        if analyzer is not None and phase > 0:
            got = analyzer.phase(positions[phase], phase_index=phase, num_phases=motion.num_phases)
            true = analyzer.phase(
                motion.position(X, phase), phase_index=phase, num_phases=motion.num_phases
            )
            if got.twist_deg.size == true.twist_deg.size and got.twist_deg.size:
                row['twist_error_deg'] = float(np.max(np.abs(got.twist_deg - true.twist_deg)))
                if sa_span is not None:
                    inside = ~levels_outside(got.level_position, sa_span)
                    if inside.any():
                        row['twist_error_measured_deg'] = float(
                            np.max(np.abs(got.twist_deg - true.twist_deg)[inside])
                        )
                    if not inside.all():
                        # the extrapolated levels' errors against what the run states for them
                        row['twist_extrapolated_over_stated'] = float(
                            np.max(
                                np.abs(got.twist_deg - true.twist_deg)[~inside]
                                / twist_extrapolation_bound(got.level_position, sa_span)[~inside]
                            )
                        )
                row['radius_error_mm'] = float(
                    np.max(np.abs(got.sa_radius_mm - true.sa_radius_mm))
                )
                row['true_twist_range_deg'] = float(np.ptp(true.twist_deg))
            if got.segment_ecc.size == true.segment_ecc.size == 17:
                # Regional strain: AHA segments with data in both (Ecc, Err, Ell; Green–Lagrange).
                ok = (got.segment_count > 0) & (true.segment_count > 0)
                for name in ('ecc', 'err', 'ell'):
                    g, t = (
                        getattr(got, f'segment_{name}')[ok],
                        getattr(true, f'segment_{name}')[ok],
                    )
                    row[f'{name}_segment_error'] = float(np.max(np.abs(g - t)))
                    row[f'{name}_global_error'] = float(abs(np.mean(g) - np.mean(t)))
                    row[f'true_{name}_global'] = float(np.mean(t))
        out['per_phase'].append(row)
    es = int(round(motion.es_phase))
    out['es_phase'] = es
    out['es'] = next((r for r in out['per_phase'] if r['phase'] == es), None)
    return out


def myocardium_coverage(X_ed: np.ndarray, motion, n: int = 4000, seed: int = 0) -> float:
    """
    Fraction of the true ED myocardium that the model covers.

    A uniform sample of the truth's myocardium counts as covered where a particle lies within
    twice the particles' median nearest-neighbour spacing.

    Parameters
    ----------
    X_ed : ndarray, shape (N, 3)
        Registered ED particles, mm.
    motion : LVMotion
        Ground truth (``sample_myocardium``).
    n, seed : int
        Sample size and its seed.

    Returns
    -------
    float
        0..1.

    """
    X = np.asarray(X_ed, dtype=np.float64)
    tree = cKDTree(X)
    spacing = float(np.median(tree.query(X, k=2)[0][:, 1]))
    dist, _ = tree.query(motion.sample_myocardium(n, seed=seed))
    return float(np.mean(dist <= 2.0 * spacing))
