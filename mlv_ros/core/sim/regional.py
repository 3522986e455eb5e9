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
Regional wall-motion abnormalities of the simulated LV and their ground truth.

Regions
-------
A *region* is a mapping (preset ``motion.regions`` list, protocol item ``abnormal_regions``)::

    {kind: dyskinetic, levels: [0.0, 0.3], centre_deg: 0.0, width_deg: 360.0, contraction: -0.5}

* ``kind``: ``hypokinetic`` (reduced), ``akinetic`` (no contraction, no thickening: Err, Ecc,
  Ell ≈ 0, each level of the region moves rigidly; it still twists with the heart, so the
  torsional shear E_cl of its neighbours remains) or ``dyskinetic`` (moves the wrong way: at ES its
  wall thins and stretches and its endocardium bulges outward, e.g. an apical aneurysm).
* ``levels``: ``[lo, hi]`` fractions of the ED apex-to-base length from the epicardial apex
  (0 apex, 1 base plane). ``lo = 0`` takes in the apex tip fully, ``hi = 1`` the base plane.
* ``centre_deg``, ``width_deg``: the sector, degrees, counter-clockwise seen from the apex from
  the mid-septum (the motion's θ; AHA centres in :data:`mlv_ros.core.sim.motion._RING6`);
  ``width_deg = 360`` is a whole ring.
* ``contraction``: the fraction of the heart's normal systolic motion the region keeps — 1
  normal, 0 akinetic, below 0 dyskinetic (−0.5: it moves half as far as a normal region would,
  the other way). Optional; accepted and default values per kind in :data:`CONTRACTION`.
* ``blend_deg`` (default 30), ``blend_fraction`` (default 0.1): widths of the C² blends centred
  on the sector's sides and on its lower/upper level (the nominal edges are the 50 % points).

Rules (``ValueError`` otherwise): a sector (``width_deg < 360``) starts at least
``blend_fraction`` above the apex tip (the solid apical wall below the cavity, level
``1 − endo_depth / length``), where an angular window would meet the long axis and make the
motion discontinuous; two regions must not overlap, blends included (their levels or their
sectors apart).

Ground truth
------------
:func:`regional_truth` gives, per AHA segment at ES, the Green–Lagrange strain of the analytic
motion (Err, Ecc, Ell in the cylindrical radial / circumferential / longitudinal frame of
:func:`mlv_ros.core.analysis.frame.cardiac_coordinates` built on the true long axis and septum,
the analyzer's definitions), the prescribed contraction and a class: :data:`CLASS_THRESHOLDS`
on the *median* contraction ``c̃`` over the segment's volume (the class at least half of the
segment has): normal ``c̃ ≥ 0.75``, hypokinetic ``0.2 ≤ c̃ < 0.75``, akinetic
``−0.2 ≤ c̃ < 0.2``, dyskinetic ``c̃ < −0.2``. Strain in a region's blends (the hinge between
a bulging and a contracting wall) is large, so a segment's mean strain can be far from its
core's; the truth keeps the mean (what a particle average measures).
"""

from __future__ import annotations

import math

import numpy as np

REGION_KINDS = ('hypokinetic', 'akinetic', 'dyskinetic')
#: kind -> (lowest accepted, highest accepted, default) contraction.
CONTRACTION = {
    'hypokinetic': (0.1, 0.9, 0.5),
    'akinetic': (-0.1, 0.1, 0.0),
    'dyskinetic': (-1.0, -0.1, -0.5),
}
# Wide blends: the endocardial radius of a dyskinetic region differs from its contracting
# neighbours' by up to ~0.4 R at ES, and the hinge takes it over one blend width.
DEFAULT_BLEND_DEG = 30.0
DEFAULT_BLEND_FRACTION = 0.1
_KEYS = ('kind', 'levels', 'centre_deg', 'width_deg', 'contraction', 'blend_deg', 'blend_fraction')
#: Truth class of a segment from its median contraction: the first class whose bound it reaches.
CLASS_THRESHOLDS = (
    ('normal', 0.75),
    ('hypokinetic', 0.2),
    ('akinetic', -0.2),
    ('dyskinetic', -math.inf),
)
CLASSES = tuple(name for name, _ in CLASS_THRESHOLDS)
#: AHA segment number (1–17) of each ring's sector order used by the analyzer's frame: the
#: analyzer measures θ from its reference; with the mid-septum as reference the anterior
#: insertion is at θ = −60° (see :class:`~mlv_ros.core.analysis.frame.LVFrame`).
AHA_ORIGIN_FROM_SEPTUM_DEG = -60.0


def _number(v, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ValueError(f'{what} must be a number, got {v!r}')
    v = float(v)
    if not math.isfinite(v):
        raise ValueError(f'{what} must be finite, got {v}')
    return v


def normalise_region(region, where: str = 'region') -> dict:
    """
    Check one region mapping and fill its defaults.

    Parameters
    ----------
    region : dict
        See the module docstring.
    where : str
        Name used in error messages.

    Returns
    -------
    dict
        Every key of the module docstring, plain floats, ``levels`` a list of two.

    Raises
    ------
    ValueError
        Not a mapping, an unknown or missing key, or a value out of range (message names it).

    """
    if not isinstance(region, dict):
        raise ValueError(
            f'{where} must be a mapping with kind, levels, centre_deg, width_deg, got '
            f'{type(region).__name__}'
        )
    unknown = [k for k in region if k not in _KEYS]
    if unknown:
        raise ValueError(f'{where}: unknown key {unknown[0]!r}; known: {", ".join(_KEYS)}')
    for k in ('kind', 'levels', 'centre_deg', 'width_deg'):
        if k not in region:
            raise ValueError(f'{where}: missing key {k!r}')
    kind = region['kind']
    if kind not in REGION_KINDS:
        raise ValueError(f'{where}: kind = {kind!r}; allowed: {" | ".join(REGION_KINDS)}')
    lv = region['levels']
    if not isinstance(lv, (list, tuple, np.ndarray)) or len(lv) != 2:
        raise ValueError(f'{where}: levels must be [lo, hi], got {lv!r}')
    lo, hi = (_number(x, f'{where}: levels') for x in lv)
    if not 0.0 <= lo < hi <= 1.0 or hi - lo < 0.05:
        raise ValueError(
            f'{where}: levels = [{lo:g}, {hi:g}]; allowed: 0 ≤ lo < hi ≤ 1, hi − lo ≥ 0.05'
        )
    centre = _number(region['centre_deg'], f'{where}: centre_deg')
    if not 0.0 <= centre < 360.0:
        raise ValueError(f'{where}: centre_deg = {centre:g}; allowed: 0 ≤ x < 360')
    width = _number(region['width_deg'], f'{where}: width_deg')
    if not 30.0 <= width <= 360.0:
        raise ValueError(f'{where}: width_deg = {width:g}; allowed: 30 … 360 (360: a whole ring)')
    c_lo, c_hi, c_def = CONTRACTION[kind]
    c = _number(region.get('contraction', c_def), f'{where}: contraction')
    if not c_lo <= c <= c_hi:
        raise ValueError(f'{where}: contraction = {c:g} for {kind}; allowed: {c_lo:g} … {c_hi:g}')
    bd = _number(region.get('blend_deg', DEFAULT_BLEND_DEG), f'{where}: blend_deg')
    if not 5.0 <= bd <= min(60.0, width) and width < 360.0:
        raise ValueError(f'{where}: blend_deg = {bd:g}; allowed: 5 … min(60, width_deg)')
    bf = _number(region.get('blend_fraction', DEFAULT_BLEND_FRACTION), f'{where}: blend_fraction')
    if not 0.02 <= bf <= min(0.2, hi - lo):
        raise ValueError(f'{where}: blend_fraction = {bf:g}; allowed: 0.02 … min(0.2, hi − lo)')
    return {
        'kind': kind,
        'levels': [lo, hi],
        'centre_deg': centre,
        'width_deg': width,
        'contraction': c,
        'blend_deg': bd,
        'blend_fraction': bf,
    }


def apex_tip_level(geometry: dict) -> float:
    """
    Level (fraction of the length) of the endocardial apex: below it the wall is solid.

    Parameters
    ----------
    geometry : dict
        A preset's ``geometry`` section.

    """
    if geometry['kind'] != 'prolate':
        return 0.0
    L = float(geometry['length_mm'])
    return (L - float(geometry['endo_depth_mm'])) / L


def _level_span(r: dict) -> tuple[float, float]:
    """Levels a region touches, blends included (apex/base ends open)."""
    lo, hi = r['levels']
    w = r['blend_fraction']
    return (-math.inf if lo == 0.0 else lo - 0.5 * w), (math.inf if hi == 1.0 else hi + 0.5 * w)


def _sector_span(r: dict) -> tuple[float, float] | None:
    """(start, width) in degrees of the angles a region touches, blends included; None = all."""
    if r['width_deg'] >= 360.0:
        return None
    full = r['width_deg'] + r['blend_deg']
    if full >= 360.0:
        return None
    return (r['centre_deg'] - 0.5 * full) % 360.0, full


def regions_overlap(a: dict, b: dict) -> bool:
    """Whether two normalised regions touch (blends included)."""
    la, lb = _level_span(a), _level_span(b)
    if la[1] <= lb[0] or lb[1] <= la[0]:
        return False
    sa, sb = _sector_span(a), _sector_span(b)
    if sa is None or sb is None:
        return True
    d = (sb[0] - sa[0]) % 360.0  # start of b after the start of a, CCW
    return d < sa[1] or 360.0 - d < sb[1]


def check_regions(regions, geometry: dict, others=(), where: str = 'regions') -> list[dict]:
    """
    Normalise regions and check them against a heart's geometry and each other.

    Parameters
    ----------
    regions : list of dict
        See the module docstring.
    geometry : dict
        The preset's ``geometry`` (for the apex tip level).
    others : sequence of dict
        Already normalised regions they must not overlap (e.g. the preset's own).
    where : str
        Name used in error messages.

    Returns
    -------
    list of dict

    Raises
    ------
    ValueError
        As :func:`normalise_region`, a sector reaching the apex tip, or two regions overlapping.

    """
    if not isinstance(regions, (list, tuple)):
        raise ValueError(f'{where} must be a list of regions, got {type(regions).__name__}')
    tip = apex_tip_level(geometry)
    out = []
    for i, reg in enumerate(regions):
        r = normalise_region(reg, f'{where}[{i}]')
        low = tip + r['blend_fraction']
        if r['width_deg'] < 360.0 and r['levels'][0] < low - 1e-9:
            raise ValueError(
                f'{where}[{i}]: a sector (width_deg < 360) must start at level ≥ {low:.3f} (the '
                f'apex tip, solid wall below level {tip:.3f}, plus blend_fraction); got levels '
                f'{r["levels"]}: start higher or make it a whole ring (width_deg 360)'
            )
        for j, o in enumerate([*others, *out]):
            if regions_overlap(r, o):
                raise ValueError(
                    f'{where}[{i}] overlaps another region ({o["kind"]} at levels '
                    f'{o["levels"]}, centre {o["centre_deg"]:g}°, width '
                    f'{o["width_deg"]:g}°, blends included); move it apart'
                )
        out.append(r)
    return out


# --------------------------------------------------------------------------- ground truth
def classify_contraction(c) -> np.ndarray:
    """
    Return the truth class name per segment mean contraction (:data:`CLASS_THRESHOLDS`).

    Parameters
    ----------
    c : array_like, shape (K,)
        Segment mean contractions (dimensionless).

    Returns
    -------
    ndarray of str, shape (K,)

    """
    c = np.asarray(c, dtype=np.float64)
    out = np.full(c.shape, CLASSES[-1], dtype=object)
    for name, bound in reversed(CLASS_THRESHOLDS[:-1]):
        out[c >= bound] = name
    return out


def truth_frame(motion):
    """
    Return the analyzer's :class:`~mlv_ros.core.analysis.frame.LVFrame` on the truth's axis.

    Apex = ED epicardial apex, base = base-plane centre, reference = mid-septum with the AHA
    origin at −60° (so the analyzer's segments are the motion's AHA windows).
    """
    from mlv_ros.core.analysis.frame import LVFrame

    f = motion.frame
    return LVFrame(f.apex, f.base_centre, f.septum, aha_origin_deg=AHA_ORIGIN_FROM_SEPTUM_DEG)


def strain_components(motion, X_ed, phase, frame=None) -> np.ndarray:
    """
    Return the true Green–Lagrange normal strains of ED points, cylindrical frame.

    Parameters
    ----------
    motion : LVMotion
        Ground-truth LV geometry and motion.
    X_ed : ndarray, shape (N, 3)
        ED positions, mm.
    phase : int or float
        Phase index.
    frame : LVFrame, optional
        Default :func:`truth_frame`.

    Returns
    -------
    ndarray, shape (N, 3)
        ``[E_rr, E_cc, E_ll]`` (dimensionless; negative = shortening/thinning).

    """
    from mlv_ros.core.analysis.frame import cardiac_coordinates
    from mlv_ros.core.analysis.strain import cardiac_strain, green_lagrange

    X = np.asarray(X_ed, dtype=np.float64).reshape(-1, 3)
    c = cardiac_coordinates(X, frame or truth_frame(motion))
    e = cardiac_strain(green_lagrange(motion.deformation_gradient(X, phase)), c.e_r, c.e_c, c.e_l)
    return np.stack([e['rr'], e['cc'], e['ll']], axis=1)


def truth_segments(motion, X_ed, frame=None) -> np.ndarray:
    """AHA segment (1–17) of ED points in the truth frame, shape (N,)."""
    from mlv_ros.core.analysis.frame import cardiac_coordinates
    from mlv_ros.core.analysis.strain import aha_segments

    fr = frame or truth_frame(motion)
    c = cardiac_coordinates(np.asarray(X_ed, dtype=np.float64).reshape(-1, 3), fr)
    return aha_segments(c.h, c.theta, fr.aha_origin_deg)


def regional_truth(motion, n_points: int = 20000, seed: int = 0, phase=None) -> dict:
    """
    Per-AHA-segment ground truth at end-systole (JSON-ready).

    Segment means over a uniform sample of the ED myocardium (volume means, as the analyzer's
    particle means).

    Parameters
    ----------
    motion : LVMotion
        Ground-truth LV geometry and motion (with its abnormal regions).
    n_points : int
        Sample size (20000: sampling error of a segment mean ≈ 0.005 in Err).
    seed : int
        Sample seed.
    phase : int, optional
        Default the integer phase nearest ES, ``round(motion.es_phase)`` (the phases a run
        delivers; as :func:`mlv_ros.core.sim.evaluation.evaluate_run`).

    Returns
    -------
    dict
        ``phase``, ``n_points``, ``frame`` (the LVFrame dict), ``class_thresholds``
        (name → lowest mean contraction), ``regions`` (the motion's normalised regions),
        ``segments``: 17 dicts (AHA order) ``segment``, ``name``, ``err``, ``ecc``, ``ell``
        (mean Green–Lagrange strain), ``contraction`` and ``median_contraction`` (mean and
        median prescribed contraction; the class follows the median),
        ``abnormal_fraction`` (share of its volume with contraction < 0.2), ``class``,
        ``count`` (sample points); ``global``: ``err``, ``ecc``, ``ell`` (means over all
        points).

    """
    from mlv_ros.core.analysis.strain import AHA_SEGMENT_NAMES, segment_means

    if int(n_points) < 170:
        raise ValueError(f'n_points must be >= 170 (10 per segment), got {n_points}')
    es = int(round(motion.es_phase)) if phase is None else int(phase)
    fr = truth_frame(motion)
    X = motion.sample_myocardium(int(n_points), seed=seed)
    seg = truth_segments(motion, X, fr)
    E = strain_components(motion, X, es, fr)
    c = motion.contraction(X)
    means = {}
    for i, name in enumerate(('err', 'ecc', 'ell')):
        means[name], count = segment_means(E[:, i], seg)
    means['contraction'], _ = segment_means(c, seg, fill=1.0)
    means['median_contraction'] = np.array(
        [np.median(c[seg == k]) if np.any(seg == k) else 1.0 for k in range(1, 18)]
    )
    means['abnormal_fraction'], _ = segment_means((c < 0.2).astype(float), seg)
    cls = classify_contraction(means['median_contraction'])
    segments = [
        {
            'segment': k + 1,
            'name': AHA_SEGMENT_NAMES[k],
            **{m: round(float(means[m][k]), 5) for m in means},
            'class': str(cls[k]),
            'count': int(count[k]),
        }
        for k in range(17)
    ]
    return {
        'phase': es,
        'n_points': int(n_points),
        'frame': fr.to_dict(),
        'class_thresholds': {
            n: (None if not math.isfinite(b) else b) for n, b in CLASS_THRESHOLDS
        },
        'regions': [dict(r) for r in motion.regions],
        'segments': segments,
        'global': {
            m: round(float(np.mean(E[:, i])), 5) for i, m in enumerate(('err', 'ecc', 'ell'))
        },
    }
