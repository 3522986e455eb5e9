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
Randomised acquisition protocols: any tagged study, not only ours.

A *protocol* is a flat mapping ``item -> value`` that names every acquisition choice the
simulator and the DICOM writer make: the heart (shape, orientation, position), the tag grid,
the matrix, the slices, timing, contrast, the SA stack's order and normal sign, and how the
files encode it all (:data:`ITEMS` lists them with units and ranges; README "Random
protocols" has the table).

Items are scalars or lists, except ``abnormal_regions``: a list of mappings
(:mod:`mlv_ros.core.sim.regional`).

* :func:`draw_protocol` draws every item from its documented range. Each item has its own
  random stream, keyed by ``(seed, item name)``, so fixing one item leaves every other item's
  draw unchanged, except where a range depends on another item (the matrix and the tag period on
  the pixel spacing, the SA stack and the abnormal regions on the shape, the background intensity
  on its kind, the LA angles and flips on the plane count, the intercept on the rescale).
* :func:`complete_protocol` fills a partial protocol from the shape's preset (today's fixed
  protocol), so ``{}`` means the ``normal`` preset exactly.
* :func:`protocol_preset` turns a protocol into a preset dict for
  :func:`~mlv_ros.core.sim.study.simulate_study`; the preset carries the protocol under
  ``"protocol"`` (so the ground truth does too).
* :func:`dicom_options` gives the matching keyword arguments of
  :func:`~mlv_ros.core.io.dicom.write_study_dicom`.

Every value a caller gives is checked against its *accepted* range (wider than the drawn one,
e.g. small matrices and few phases for tests); a bad one raises ``ValueError`` naming the item
and what is allowed. Units: mm, s, degrees; positions in DICOM patient coordinates (LPS).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
import math
from pathlib import Path
from typing import Any, Callable
import zlib

from mlv_ros.core.sim.presets import load_preset
from mlv_ros.core.sim.regional import apex_tip_level, check_regions, normalise_region, REGION_KINDS
import numpy as np
import yaml

SHAPES = ('normal', 'hypertrophic', 'dilated', 'infarct')
#: Apex → base of a human heart points right-posterior-superior (LPS); the DICOM reader's prior.
BASE_SIDE = np.array([-1.0, 1.0, 1.0]) / math.sqrt(3.0)
#: Drawn long axes lie within this angle of :data:`BASE_SIDE` ...
AXIS_CONE_DEG = 40.0
#: ... and at least this far from every scanner axis (no near-axial/coronal/sagittal hearts).
AXIS_MIN_OFF_SCANNER_DEG = 20.0
#: Accepted long axes: within this angle of :data:`BASE_SIDE` (the reader orients the axis by it).
AXIS_ACCEPT_DEG = 85.0
#: SA stack margins used by the draw: the most apical slice at least this far above the
#: epicardial apex, the most basal one at least ``base_descent_mm + SA_BASE_MARGIN_MM`` below
#: the ED base plane (so it stays inside the LV through systole).
SA_APEX_MARGIN_MM = 10.0
SA_BASE_MARGIN_MM = 1.0
#: LA planes are distinct by at least this angle (modulo 180°); draws keep 1° more.
LA_MIN_SEPARATION_DEG = 20.0
#: The stored tag period is at least this many pixels in a draw (2 are accepted).
MIN_TAG_PX_DRAWN = 3.5
MIN_TAG_PX = 2.0
#: A drawn field of view (size × pixel spacing), mm, and the largest drawn matrix.
FOV_RANGE_MM = (200.0, 380.0)
MAX_DRAWN_SIZE = 256
#: Stored units per intensity unit when ``dicom_range_fill`` is null (the writer's default).
LEGACY_PIXEL_SCALE = 1000.0
#: A line pair's second family: drawn this far (deg) from the first, accepted within the other.
PAIR_ANGLE_DRAWN = (45.0, 135.0)
PAIR_ANGLE_ACCEPTED = (30.0, 150.0)
#: Breath-hold shift of a line pair's second series (drawn): in-plane length up to this, mm, and
#: through-plane within ± the other. End-expiratory breath-holds put the heart 1–5 mm apart
#: (McLeish et al., IEEE TMI 21(9) 2002, 1142–1150; Holland et al., Radiology 209 1998, 483–489).
PAIR_SHIFT_DRAWN_MM = 4.0
PAIR_THROUGH_DRAWN_MM = 3.0
#: The line-pair items' values in every study that is not a pair (and in fixed protocols).
PAIR_DEFAULTS = {
    'line_pair_angle_deg': 90.0,
    'line_pair_shift_mm': [0.0, 0.0],
    'line_pair_through_mm': 0.0,
}
#: What ``tag_lines`` is drawn from with ``tag_lines='any'``: grid, pair, single.
TAG_LINES_ANY = (('grid', 'pair', 'single'), (0.5, 0.3, 0.2))


@dataclass(frozen=True)
class Item:
    """
    One protocol item.

    Attributes
    ----------
    name : str
    doc : str
        Meaning and unit.
    drawn : str
        The range :func:`draw_protocol` draws from, in words.
    accepted : str
        What a given value may be, in words (named in the error message).
    check : callable
        ``check(value) -> normalised value``; raises ``ValueError`` (any message) when bad.

    """

    name: str
    doc: str
    drawn: str
    accepted: str
    check: Callable[[Any], Any]


# --------------------------------------------------------------------------- value checks
def _num(v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ValueError('not a number')
    v = float(v)
    if not math.isfinite(v):
        raise ValueError('not finite')
    return v


def _float(lo: float, hi: float, hi_open: bool = False):
    def check(v):
        v = _num(v)
        if not (lo <= v and (v < hi if hi_open else v <= hi)):
            raise ValueError('out of range')
        return v

    return check


def _int(lo: int, hi: int):
    def check(v):
        v = _num(v)
        if v != int(v) or not lo <= v <= hi:
            raise ValueError('out of range')
        return int(v)

    return check


def _choice(options):
    def check(v):
        if isinstance(v, bool) or v not in options:
            raise ValueError('not a choice')
        return v

    return check


def _bool(v):
    if not isinstance(v, (bool, np.bool_)):
        raise ValueError('not a bool')
    return bool(v)


def _optional(inner):
    def check(v):
        return None if v is None else inner(v)

    return check


def _vector(n: int, lo: float, hi: float):
    def check(v):
        if not isinstance(v, (list, tuple, np.ndarray)) or len(v) != n:
            raise ValueError('wrong length')
        return [_float(lo, hi)(x) for x in v]

    return check


def _long_axis(v):
    a = np.array(_vector(3, -1e3, 1e3)(v))
    norm = float(np.linalg.norm(a))
    if norm < 1e-6:
        raise ValueError('zero vector')
    if float(a @ BASE_SIDE) / norm < math.cos(math.radians(AXIS_ACCEPT_DEG)):
        raise ValueError('not on the base side')
    return [float(x) for x in a]


def _angle_list(v):
    if not isinstance(v, (list, tuple, np.ndarray)):
        raise ValueError('not a list')
    return [_float(0.0, 180.0, hi_open=True)(x) for x in v]


class _Why(ValueError):
    """A check failure whose message is worth showing (the item's error message quotes it)."""


#: At most this many abnormal regions in a protocol.
MAX_REGIONS = 3


def _regions(v):
    if not isinstance(v, (list, tuple)):
        raise _Why('not a list of regions')
    if len(v) > MAX_REGIONS:
        raise _Why(f'{len(v)} regions, at most {MAX_REGIONS}')
    try:
        return [normalise_region(r, f'region {i}') for i, r in enumerate(v)]
    except ValueError as exc:
        raise _Why(str(exc)) from None


def _bool_list(v):
    if not isinstance(v, (list, tuple, np.ndarray)):
        raise ValueError('not a list')
    return [_bool(x) for x in v]


# --------------------------------------------------------------------------- the items
_ITEMS = [
    # anatomy
    Item(
        'shape',
        'heart: the preset config/phantoms/<shape>.yaml (geometry and motion)',
        'normal | hypertrophic | dilated | infarct',
        'normal | hypertrophic | dilated | infarct',
        _choice(SHAPES),
    ),
    Item(
        'long_axis',
        'LV long axis apex → base, LPS (normalised on use)',
        f'uniform within {AXIS_CONE_DEG:g}° of (−1, 1, 1)/√3 and ≥ {AXIS_MIN_OFF_SCANNER_DEG:g}° '
        'from every scanner axis',
        f'3 numbers, a non-zero vector within {AXIS_ACCEPT_DEG:g}° of (−1, 1, 1) (base right-'
        'posterior-superior of the apex)',
        _long_axis,
    ),
    Item(
        'septum_deg',
        "septum direction: the shape's septum hint turned about the long axis, "
        'CCW seen from the apex, deg',
        '0 ≤ x < 360',
        '0 ≤ x < 360',
        _float(0.0, 360.0, True),
    ),
    Item(
        'base_centre_mm',
        'centre of the ED base plane, LPS mm',
        'each coordinate −50 … 50',
        '3 numbers, each −500 … 500',
        _vector(3, -500.0, 500.0),
    ),
    Item(
        'abnormal_regions',
        'regional wall-motion abnormalities (mlv_ros/core/sim/regional.py): '
        'kind, levels [lo, hi] (0 apex … 1 base), centre_deg (CCW from the septum seen from the '
        'apex), width_deg (360: a ring), contraction (share of normal motion kept)',
        'none (40 %), 1 (40 %) or 2 (20 %) regions, kind uniform; a ring from the apex to level '
        '0.15 … 0.4 (a quarter), else a 60 … 180° sector over 0.2 … 0.5 of the length above the '
        'apex tip; contraction hypokinetic 0.3 … 0.6, akinetic 0, dyskinetic −0.5 … −0.2; apart',
        f'a list of ≤ {MAX_REGIONS} regions: kind hypokinetic | akinetic | dyskinetic, levels '
        '0 ≤ lo < hi ≤ 1 (≥ 0.05 apart), centre_deg 0 … 360, width_deg 30 … 360, contraction '
        'hypokinetic 0.1 … 0.9, akinetic −0.1 … 0.1, dyskinetic −1 … −0.1, optional blend_deg '
        '5 … 60 and blend_fraction 0.02 … 0.2; sectors above the apex tip; regions apart '
        "(blends included, and from the infarct shape's own segment)",
        _regions,
    ),
    Item(
        'apex_thickening',
        'ES axial thickening of the solid apical wall (the apex cap, whose wall normal is the '
        'long axis), fraction of its ED thickness (mlv_ros/core/sim/motion.py; normal apical '
        'wall thickening ~20–60 %); null: the legacy cap, every level shortening alike (the '
        "presets' own, and studies drawn before the item existed)",
        '0.2 … 0.5',
        '0 … 0.8, or null',
        _optional(_float(0.0, 0.8)),
    ),
    Item(
        'right_ventricle',
        'a right ventricle (mlv_ros/core/sim/rv.py): blood crescent and thin '
        'tagged free wall on the septal side, insertions 120° apart about the septum direction',
        'true (75 %) | false',
        'true | false',
        _bool,
    ),
    # tag grid
    Item(
        'tag_angle_deg',
        'in-plane grid rotation from the image rows, deg',
        '0 ≤ x < 180',
        '0 ≤ x < 180',
        _float(0.0, 180.0, True),
    ),
    Item(
        'tag_lines',
        'tag line families: grid (both) | single (one family of parallel lines, ⟂ the grid '
        "angle's row direction: only motion across the lines is measured) | pair (two "
        'single-line series of every slice, the second with its lines turned by 90°, as vendors '
        'acquire them in two breath-holds)',
        'grid; with tag_lines any (mlv-ros simulate --tag-lines any): grid 50 %, pair 30 %, '
        'single 20 %',
        'grid | single | pair',
        _choice(('grid', 'single', 'pair')),
    ),
    Item(
        'line_pair_angle_deg',
        "pair: angle from the first series' tag lines to the second's, deg (each family "
        'measures along its own normal: motion along a direction between them comes from both, '
        'its error growing as 1/sin(angle))',
        f'pair: {PAIR_ANGLE_DRAWN[0]:g} … {PAIR_ANGLE_DRAWN[1]:g}; else 90',
        f'{PAIR_ANGLE_ACCEPTED[0]:g} … {PAIR_ANGLE_ACCEPTED[1]:g} (the reader pairs two '
        'families at least 30° apart)',
        _float(*PAIR_ANGLE_ACCEPTED),
    ),
    Item(
        'line_pair_shift_mm',
        "pair: where the heart sits in the second series' breath-hold relative to the first, "
        "along the SA images' row and column directions (ImageOrientationPatient's order), mm "
        '(the DICOM geometry does not say so)',
        f'pair: a random direction, length 0 … {PAIR_SHIFT_DRAWN_MM:g}; else 0, 0',
        '2 numbers, each −20 … 20',
        _vector(2, -20.0, 20.0),
    ),
    Item(
        'line_pair_through_mm',
        'pair: the same shift along the long axis (apex → base), mm: through the SA planes',
        f'pair: −{PAIR_THROUGH_DRAWN_MM:g} … {PAIR_THROUGH_DRAWN_MM:g}; else 0',
        '−20 … 20',
        _float(-20.0, 20.0),
    ),
    Item(
        'tag_spacing_mm',
        'tag period λ, mm',
        f'max(5, {MIN_TAG_PX_DRAWN:g} px) … 10',
        f'2 … 20 and ≥ {MIN_TAG_PX:g} pixels',
        _float(2.0, 20.0),
    ),
    # matrix
    Item(
        'pixel_spacing_mm',
        'pixel spacing (rows = columns), mm',
        '1.0 … 2.0',
        '0.3 … 4.0',
        _float(0.3, 4.0),
    ),
    Item(
        'size',
        'matrix rows = columns, px',
        f'field of view {FOV_RANGE_MM[0]:g} … {FOV_RANGE_MM[1]:g} mm, ≤ {MAX_DRAWN_SIZE} px',
        'integer 16 … 1024',
        _int(16, 1024),
    ),
    # slices
    Item('slice_thickness_mm', 'slab thickness (FWHM), mm', '5 … 10', '1 … 20', _float(1.0, 20.0)),
    Item(
        'sa_slices',
        'SA slices',
        '6 … 14, as many as fit at 6 mm (normal ≤ 11)',
        'integer 2 … 40',
        _int(2, 40),
    ),
    Item(
        'sa_spacing_mm',
        'SA centre-to-centre spacing, mm',
        '6 … 12, as far as the stack fits',
        '1 … 30, the stack inside the LV',
        _float(1.0, 30.0),
    ),
    Item(
        'sa_base_gap_mm',
        'ED base plane to the most basal SA slice, mm',
        f'stack placed at random between base_descent + {SA_BASE_MARGIN_MM:g} mm below the base '
        f'and {SA_APEX_MARGIN_MM:g} mm above the apex',
        '0 … 200, the stack inside the LV',
        _float(0.0, 200.0),
    ),
    Item('la_planes', 'LA planes through the long axis', '2 … 6', 'integer 0 … 9', _int(0, 9)),
    Item(
        'la_angles_deg',
        'LA plane angles from the septum, CCW seen from the apex, deg',
        f'random start; equal (180°/n) or random steps ≥ {LA_MIN_SEPARATION_DEG + 1:g}°',
        f'la_planes angles 0 ≤ x < 180, ≥ {LA_MIN_SEPARATION_DEG:g}° apart (mod 180)',
        _angle_list,
    ),
    Item(
        'la_flip',
        'per LA plane: normal reversed (row direction mirrored)',
        'each true | false',
        'la_planes booleans',
        _bool_list,
    ),
    Item(
        'sa_inplane_deg',
        'SA image rows turned from the septum toward the columns, deg',
        '0 ≤ x < 360',
        '0 ≤ x < 360',
        _float(0.0, 360.0, True),
    ),
    Item(
        'la_inplane_deg',
        'LA images turned about their normal, deg (0: base at the top)',
        '−30 … 30',
        '−180 … 180',
        _float(-180.0, 180.0),
    ),
    Item(
        'sa_fov_shift_mm',
        'SA image centre off the long axis along rows, columns, mm',
        'each −25 … 25',
        '2 numbers, each −100 … 100',
        _vector(2, -100.0, 100.0),
    ),
    Item(
        'la_fov_shift_mm',
        'LA image centre off the axis midpoint along rows, columns, mm',
        'each −25 … 25',
        '2 numbers, each −100 … 100',
        _vector(2, -100.0, 100.0),
    ),
    # timing
    Item('num_phases', 'cine phases per cycle', '16 … 40', 'integer 2 … 200', _int(2, 200)),
    Item('cycle_duration_s', 'RR interval, s', '0.7 … 1.2', '0.3 … 2.0', _float(0.3, 2.0)),
    Item('t1_s', 'tag fading time constant T1, s', '0.8 … 1.2', '0.1 … 5.0', _float(0.1, 5.0)),
    # contrast
    Item(
        'snr',
        'myocardium / Rician noise σ (null: noiseless)',
        '10 … 40',
        '1 … 1000 or null',
        _optional(_float(1.0, 1000.0)),
    ),
    Item(
        'background',
        'tissue around the heart',
        'none | untagged | tagged',
        'none | untagged | tagged',
        _choice(('none', 'untagged', 'tagged')),
    ),
    Item(
        'background_m0',
        'its signal, × myocardium',
        'none: 0; untagged 0.05 … 0.2; tagged 0.2 … 0.5',
        '0 … 2 (0 exactly for none)',
        _float(0.0, 2.0),
    ),
    Item(
        'blood_m0',
        'blood signal, × myocardium (bright blood above 1)',
        '0.3 … 1.3',
        '0 … 3',
        _float(0.0, 3.0),
    ),
    # stack order and normals
    Item(
        'sa_order',
        'SA slice index 0 (and the first SA series) at',
        'base_first | apex_first',
        'base_first | apex_first',
        _choice(('base_first', 'apex_first')),
    ),
    Item(
        'sa_normal',
        'SA normal (row × column) points',
        'base_to_apex | apex_to_base',
        'base_to_apex | apex_to_base',
        _choice(('base_to_apex', 'apex_to_base')),
    ),
    # DICOM encoding
    Item(
        'dicom_bits',
        'BitsStored (8: BitsAllocated 8, else 16)',
        '8 | 12 | 16',
        '8 | 12 | 16',
        _choice((8, 12, 16)),
    ),
    Item(
        'dicom_rescale',
        'RescaleSlope/RescaleIntercept written (false: stored values only)',
        'true | false',
        'true | false',
        _bool,
    ),
    Item(
        'dicom_rescale_intercept',
        'RescaleIntercept, intensity units',
        '−0.5 … 0 with a rescale, else 0',
        '−100 … 0; 0 without a rescale',
        _float(-100.0, 0.0),
    ),
    Item(
        'dicom_range_fill',
        "fraction of the stored range the study's brightest pixel uses "
        f'(null: {LEGACY_PIXEL_SCALE:g} stored units per intensity unit)',
        '0.5 … 0.95',
        '0.05 … 1 or null (null with 16 bits only)',
        _optional(_float(0.05, 1.0)),
    ),
    Item(
        'dicom_sa_series',
        'SA slices: one series each, or one multi-slice series',
        'per_slice | single',
        'per_slice | single',
        _choice(('per_slice', 'single')),
    ),
    Item(
        'dicom_instance_numbers',
        'InstanceNumber: phase + 1 per slice, or running across slices',
        'per_slice | across_slices',
        'per_slice | across_slices',
        _choice(('per_slice', 'across_slices')),
    ),
    Item(
        'dicom_file_names',
        'file layout: <view>_<index>/IM_<n>.dcm, or random nested names',
        'ordered | random',
        'ordered | random',
        _choice(('ordered', 'random')),
    ),
]
#: Every protocol item, in the order protocols are written.
ITEMS: dict[str, Item] = {it.name: it for it in _ITEMS}


def _bad(name: str, value, why: str | None = None) -> ValueError:
    it = ITEMS[name]
    extra = f' ({why})' if why else ''
    return ValueError(
        f'protocol: {name} = {value!r} is not allowed{extra}; allowed: {it.accepted}'
    )


def check_items(values: dict) -> dict:
    """
    Check each given item against its accepted range (no cross-item checks).

    Parameters
    ----------
    values : dict
        ``item -> value``; any subset of :data:`ITEMS`.

    Returns
    -------
    dict
        The values normalised (ints, floats, lists, in :data:`ITEMS` order).

    Raises
    ------
    ValueError
        An unknown item, or a value outside its accepted range (the message names the item and
        what is allowed).

    """
    if not isinstance(values, dict):
        raise ValueError(f'protocol: a mapping of items is required, got {type(values).__name__}')
    unknown = [k for k in values if k not in ITEMS]
    if unknown:
        raise ValueError(f'protocol: unknown item {unknown[0]!r}; known items: {", ".join(ITEMS)}')
    out = {}
    for name, it in ITEMS.items():
        if name in values:
            try:
                out[name] = it.check(values[name])
            except _Why as exc:
                raise _bad(name, values[name], str(exc)) from None
            except (ValueError, TypeError):
                raise _bad(name, values[name]) from None
    return out


# --------------------------------------------------------------------------- shapes
@lru_cache(maxsize=None)
def _shape(shape: str) -> dict:
    """
    Return the preset facts a protocol needs.

    Length, base descent, the preset's own protocol values and abnormal regions.
    """
    p = load_preset(shape)
    g, m, im = p['geometry'], p['motion'], p['imaging']
    L = float(g['length_mm'])
    n = int(im['sa_slices'])
    b, a = float(im['sa_base_gap_mm']), float(im['sa_apex_gap_mm'])
    from mlv_ros.core.sim.motion import infarct_region  # motion imports this module's neighbours

    regions = [infarct_region(m['infarct'])] if m.get('infarct') else []
    return {
        'length': L,
        'descent': float(m['base_descent_mm']),
        'n': n,
        'base_gap': b,
        'apex_gap': a,
        'preset': p,
        'regions': regions,
    }


def _sa_room(shape: str) -> tuple[float, float]:
    """(lowest drawn base gap, room for the stack between the draw's margins), mm."""
    s = _shape(shape)
    base_min = s['descent'] + SA_BASE_MARGIN_MM
    return base_min, s['length'] - base_min - SA_APEX_MARGIN_MM


def default_protocol(shape: str = 'normal') -> dict:
    """
    Return the fixed protocol of a shape's preset, as protocol items (every item).

    Parameters
    ----------
    shape : str
        One of :data:`SHAPES`.

    Returns
    -------
    dict
        ``protocol_preset(default_protocol(shape))`` simulates what the preset alone does.

    """
    if shape not in SHAPES:
        raise _bad('shape', shape)
    s = _shape(shape)
    p = s['preset']
    o, im, m = p['orientation'], p['imaging'], p['motion']
    n_la = int(im['la_planes'])
    return {
        'shape': shape,
        'long_axis': [float(x) for x in o['long_axis']],
        'septum_deg': 0.0,
        'base_centre_mm': [float(x) for x in o['base_centre_mm']],
        'abnormal_regions': [],
        'apex_thickening': (
            None if m.get('apex_thickening') is None else float(m['apex_thickening'])
        ),
        'right_ventricle': bool(p['geometry'].get('rv')),
        'tag_angle_deg': float(im.get('tag_angle_deg', 0.0)),
        'tag_lines': str(im.get('tag_lines', 'grid')),
        **{k: list(v) if isinstance(v, list) else v for k, v in PAIR_DEFAULTS.items()},
        'tag_spacing_mm': float(im['tag_spacing_mm']),
        'pixel_spacing_mm': float(im['pixel_spacing_mm']),
        'size': int(im['size']),
        'slice_thickness_mm': float(im['slice_thickness_mm']),
        'sa_slices': s['n'],
        'sa_spacing_mm': (s['length'] - s['base_gap'] - s['apex_gap']) / (s['n'] - 1),
        'sa_base_gap_mm': s['base_gap'],
        'la_planes': n_la,
        'la_angles_deg': [k * float(im['la_angle_step_deg']) % 180.0 for k in range(n_la)],
        'la_flip': [False] * n_la,
        'sa_inplane_deg': 0.0,
        'la_inplane_deg': 0.0,
        'sa_fov_shift_mm': [0.0, 0.0],
        'la_fov_shift_mm': [0.0, 0.0],
        'num_phases': int(m['num_phases']),
        'cycle_duration_s': float(m['cycle_duration_s']),
        't1_s': float(im['t1_s']),
        'snr': float(im['snr']),
        'background': 'tagged' if float(im['background_m0']) > 0 else 'none',
        'background_m0': float(im['background_m0']),
        'blood_m0': float(im['blood_m0']),
        'sa_order': 'base_first',
        'sa_normal': 'base_to_apex',
        'dicom_bits': 16,
        'dicom_rescale': True,
        'dicom_rescale_intercept': 0.0,
        'dicom_range_fill': None,
        'dicom_sa_series': 'per_slice',
        'dicom_instance_numbers': 'per_slice',
        'dicom_file_names': 'ordered',
    }


# --------------------------------------------------------------------------- cross checks
def _la_separation(angles: list[float]) -> float:
    """Smallest angle (mod 180°) between two planes; 180 for fewer than two."""
    best = 180.0
    for i, a in enumerate(angles):
        for b in angles[i + 1:]:
            d = abs(a - b) % 180.0
            best = min(best, d, 180.0 - d)
    return best


def validate_protocol(protocol: dict) -> dict:
    """
    Check a complete protocol: every item in range and the items consistent.

    Parameters
    ----------
    protocol : dict
        Every item of :data:`ITEMS`.

    Returns
    -------
    dict
        The normalised protocol.

    Raises
    ------
    ValueError
        A missing, unknown or out-of-range item, or items that contradict each other (the tag
        period below 2 pixels, an SA stack reaching outside the LV, LA angles closer than 20° or
        not one per plane, a background kind and intensity that disagree, an intercept without
        a rescale, a null range fill with fewer than 16 bits, a line pair's angle or shift in a
        study that is not a pair).

    """
    p = check_items(protocol)
    missing = [k for k in ITEMS if k not in p]
    if missing:
        raise ValueError(f'protocol: missing item(s) {", ".join(missing)}')
    if p['tag_spacing_mm'] < MIN_TAG_PX * p['pixel_spacing_mm'] - 1e-9:
        raise _bad(
            'tag_spacing_mm',
            p['tag_spacing_mm'],
            f'{p["tag_spacing_mm"] / p["pixel_spacing_mm"]:.2f} px at pixel_spacing_mm = '
            f'{p["pixel_spacing_mm"]:g}',
        )
    L = _shape(p['shape'])['length']
    stack = (p['sa_slices'] - 1) * p['sa_spacing_mm']
    apex_gap = L - p['sa_base_gap_mm'] - stack
    if apex_gap < 0:
        raise ValueError(
            f'protocol: the SA stack does not fit in the {p["shape"]} LV ({L:g} mm): '
            'sa_base_gap_mm '
            f'{p["sa_base_gap_mm"]:g} + (sa_slices − 1) × sa_spacing_mm = '
            f'{p["sa_base_gap_mm"] + stack:g} mm; '
            f'allowed: sa_base_gap_mm + (sa_slices − 1) × sa_spacing_mm ≤ {L:g}'
        )
    try:
        check_regions(
            p['abnormal_regions'],
            _shape(p['shape'])['preset']['geometry'],
            others=_shape(p['shape'])['regions'],
            where='region',
        )
    except ValueError as exc:
        raise _bad(
            'abnormal_regions', p['abnormal_regions'], f'{exc}; shape = {p["shape"]}'
        ) from None
    if len(p['la_angles_deg']) != p['la_planes']:
        raise _bad('la_angles_deg', p['la_angles_deg'], f'la_planes = {p["la_planes"]}')
    if len(p['la_flip']) != p['la_planes']:
        raise _bad('la_flip', p['la_flip'], f'la_planes = {p["la_planes"]}')
    sep = _la_separation(p['la_angles_deg'])
    if sep < LA_MIN_SEPARATION_DEG - 1e-9:
        raise _bad('la_angles_deg', p['la_angles_deg'], f'two planes {sep:.2f}° apart')
    if p['tag_lines'] != 'pair':
        for name, default in PAIR_DEFAULTS.items():
            if p[name] != default:
                raise _bad(name, p[name], f'tag_lines = {p["tag_lines"]}: a line pair\'s item')
    if (p['background'] == 'none') != (p['background_m0'] == 0.0):
        raise _bad('background_m0', p['background_m0'], f'background = {p["background"]}')
    if not p['dicom_rescale'] and p['dicom_rescale_intercept'] != 0.0:
        raise _bad(
            'dicom_rescale_intercept', p['dicom_rescale_intercept'], 'dicom_rescale = false'
        )
    if p['dicom_range_fill'] is None and p['dicom_bits'] != 16:
        raise _bad('dicom_range_fill', None, f'dicom_bits = {p["dicom_bits"]}')
    return p


def complete_protocol(partial: dict | None = None) -> dict:
    """
    Fill a partial protocol from its shape's preset (today's fixed protocol) and check it.

    Items that depend on a given one follow it: ``la_angles_deg`` of ``n`` given planes are
    ``k · 180°/n``, ``la_flip`` all false, ``la_planes`` the number of given angles; the SA
    spacing keeps the preset's first and last slice for a given count; ``background`` follows a
    given ``background_m0`` (0: none, else tagged) and vice versa (none: 0); the intercept is 0;
    ``dicom_range_fill`` is null with 16 bits, else 0.9.

    Parameters
    ----------
    partial : dict, optional
        Any subset of :data:`ITEMS` (``shape`` defaults to ``normal``).

    Returns
    -------
    dict
        Every item.

    Raises
    ------
    ValueError
        As :func:`validate_protocol`.

    """
    given = check_items(partial or {})
    p = default_protocol(given.get('shape', 'normal'))
    s = _shape(p['shape'])
    p.update(given)
    if 'la_angles_deg' in given and 'la_planes' not in given:
        p['la_planes'] = len(given['la_angles_deg'])
    if 'la_planes' in given and 'la_angles_deg' not in given:
        p['la_angles_deg'] = [k * 180.0 / p['la_planes'] for k in range(p['la_planes'])]
    if 'la_flip' not in given:
        p['la_flip'] = [False] * p['la_planes']
    if 'sa_spacing_mm' not in given:
        p['sa_spacing_mm'] = (s['length'] - p['sa_base_gap_mm'] - s['apex_gap']) / max(
            p['sa_slices'] - 1, 1
        )
    if 'background_m0' in given and 'background' not in given:
        p['background'] = 'none' if given['background_m0'] == 0.0 else 'tagged'
    if 'background' in given and 'background_m0' not in given and given['background'] == 'none':
        p['background_m0'] = 0.0
    if 'dicom_range_fill' not in given and p['dicom_bits'] != 16:
        p['dicom_range_fill'] = 0.9
    return validate_protocol(p)


# --------------------------------------------------------------------------- drawing
def _rng(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def _uniform(r: np.random.Generator, lo: float, hi: float, nd: int) -> float:
    """Uniform in [lo, hi], rounded to ``nd`` decimals without leaving [lo, hi]."""
    q = 10.0**nd
    v = round(float(r.uniform(lo, hi)), nd)
    return float(min(max(v, math.ceil(lo * q - 1e-6) / q), math.floor(hi * q + 1e-6) / q))


def _draw_axis(r: np.random.Generator) -> list[float]:
    """Uniform direction in the cone about :data:`BASE_SIDE`, off every scanner axis."""
    c = BASE_SIDE
    u = np.cross(c, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(c, u)
    cos_max = math.cos(math.radians(AXIS_MIN_OFF_SCANNER_DEG))
    while True:
        ct = r.uniform(math.cos(math.radians(AXIS_CONE_DEG)), 1.0)
        ph = r.uniform(0.0, 2.0 * math.pi)
        st = math.sqrt(1.0 - ct * ct)
        d = ct * c + st * (math.cos(ph) * u + math.sin(ph) * w)
        d = np.round(d / np.linalg.norm(d), 6)
        if np.abs(d).max() / np.linalg.norm(d) <= cos_max:
            return [float(x) for x in d]


def _draw_la_angles(r: np.random.Generator, n: int) -> list[float]:
    """``n`` plane angles in [0, 180): random start, equal or random steps (≥ 21°)."""
    if n == 0:
        return []
    start = r.uniform(0.0, 180.0)
    if r.random() < 0.5:
        gaps = np.full(n, 180.0 / n)
    else:
        sep = LA_MIN_SEPARATION_DEG + 1.0
        gaps = sep + (180.0 - sep * n) * r.dirichlet(np.ones(n))
    angles = start + np.concatenate([[0.0], np.cumsum(gaps[:-1])])
    return [float(round(a % 180.0, 2) % 180.0) for a in angles]


def _draw_regions(r: np.random.Generator, shape: str) -> list[dict]:
    """0–2 non-overlapping abnormal regions (ranges in the ``abnormal_regions`` item)."""
    s = _shape(shape)
    geometry = s['preset']['geometry']
    low = math.ceil((apex_tip_level(geometry) + 0.1) * 100.0) / 100.0  # + the default blend
    out: list[dict] = []
    for _ in range(int(r.choice(3, p=[0.4, 0.4, 0.2]))):
        for _attempt in range(50):  # a few redraws where a second region would overlap
            kind = REGION_KINDS[int(r.integers(len(REGION_KINDS)))]
            c = {
                'hypokinetic': _uniform(r, 0.3, 0.6, 2),
                'akinetic': 0.0,
                'dyskinetic': _uniform(r, -0.5, -0.2, 2),
            }[kind]
            if r.random() < 0.25:
                reg = {
                    'kind': kind,
                    'levels': [0.0, _uniform(r, 0.15, 0.4, 2)],
                    'centre_deg': 0.0,
                    'width_deg': 360.0,
                    'contraction': c,
                }
            else:
                length = _uniform(r, 0.2, 0.5, 2)
                lo = _uniform(r, low, max(low, 1.0 - length), 2)
                hi = min(round(lo + length, 2), 1.0)
                reg = {
                    'kind': kind,
                    'levels': [lo, 1.0 if hi >= 0.95 else hi],
                    'centre_deg': _uniform(r, 0.0, 360.0, 1) % 360.0,
                    'width_deg': _uniform(r, 60.0, 180.0, 1),
                    'contraction': c,
                }
            try:
                out.append(check_regions([reg], geometry, others=[*s['regions'], *out])[0])
                break
            except ValueError:
                continue
    return out


def _draw_shift(r: np.random.Generator) -> list[float]:
    """In-plane breath-hold shift: uniform direction, length uniform in the drawn range, mm."""
    length = float(r.uniform(0.0, PAIR_SHIFT_DRAWN_MM))
    turn = float(r.uniform(0.0, 2.0 * math.pi))
    return [round(length * math.cos(turn), 2) + 0.0, round(length * math.sin(turn), 2) + 0.0]


def draw_protocol(seed: int, fixed: dict | None = None, tag_lines: str = 'grid') -> dict:
    """
    Draw a complete acquisition protocol.

    Parameters
    ----------
    seed : int
        ≥ 0. Item ``name`` is drawn from ``numpy.random.default_rng([seed, crc32(name)])``, so
        the same seed always gives the same protocol and fixing one item does not change the
        draws of the others (except those whose range depends on it; module docstring).
    fixed : dict, optional
        Items to take as given instead of drawing them (checked against the accepted ranges;
        the draws of dependent items adapt to them).
    tag_lines : str
        ``'grid'`` (default: every seed draws the grid study it drew before single-line studies
        existed) or ``'any'``: ``tag_lines`` drawn from its own stream (:data:`TAG_LINES_ANY`),
        every other item as with ``'grid'``. A pair's angle and breath-hold shift are drawn
        from their own streams too (90°, no shift when not a pair).

    Returns
    -------
    dict
        Every item of :data:`ITEMS`, plain Python values (floats rounded to 0.01 mm/deg, 1e-3
        s, 1e-6 for the axis), in :data:`ITEMS` order.

    Raises
    ------
    ValueError
        A bad seed, an unknown or out-of-range fixed item, or fixed items that cannot be
        combined (e.g. an SA stack that does not fit in the LV).

    Notes
    -----
    SA stack: count and spacing are drawn jointly so that the stack fits the *room* between the
    draw's margins (``SA_BASE_MARGIN_MM`` below the systolic base, ``SA_APEX_MARGIN_MM`` above
    the apex): the count uniformly among 6–14 that fit at 6 mm (normal 6–11, hypertrophic 6–12,
    dilated 6–14), then the spacing uniformly in 6–12 mm as far as that count fits. The stack is
    then placed at random within the room. A stack made longer than the room by fixed items is
    shortened through the items left to draw: a fixed spacing gets fewer slices (at least 2), a
    fixed count a tighter spacing (at least 1 mm); with both fixed it is centred between the
    margins, and must still fit inside the LV.

    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f'protocol seed must be an integer >= 0, got {seed!r}')
    if tag_lines not in ('grid', 'any'):
        raise ValueError(f"tag_lines must be 'grid' or 'any', got {tag_lines!r}")
    fixed = check_items(fixed or {})
    p: dict = {}

    def pick(name, draw):
        p[name] = fixed[name] if name in fixed else draw(_rng(int(seed), name))

    pick('shape', lambda r: SHAPES[int(r.integers(len(SHAPES)))])
    pick('long_axis', _draw_axis)
    pick('septum_deg', lambda r: _uniform(r, 0.0, 360.0, 2) % 360.0)
    pick('base_centre_mm', lambda r: [_uniform(r, -50.0, 50.0, 1) for _ in range(3)])
    pick('abnormal_regions', lambda r: _draw_regions(r, p['shape']))
    pick('apex_thickening', lambda r: _uniform(r, 0.2, 0.5, 2))
    pick('right_ventricle', lambda r: bool(r.random() < 0.75))
    pick('tag_angle_deg', lambda r: _uniform(r, 0.0, 180.0, 2) % 180.0)
    kinds, odds = TAG_LINES_ANY
    pick('tag_lines', lambda r: 'grid' if tag_lines == 'grid' else kinds[int(r.choice(3, p=odds))])
    pair = p['tag_lines'] == 'pair'
    pick('line_pair_angle_deg', lambda r: _uniform(r, *PAIR_ANGLE_DRAWN, 2) if pair else 90.0)
    pick('line_pair_shift_mm', lambda r: _draw_shift(r) if pair else [0.0, 0.0])
    t = PAIR_THROUGH_DRAWN_MM
    pick('line_pair_through_mm', lambda r: _uniform(r, -t, t, 2) + 0.0 if pair else 0.0)
    pick('pixel_spacing_mm', lambda r: _uniform(r, 1.0, 2.0, 3))
    dx = p['pixel_spacing_mm']
    tag_lo = MIN_TAG_PX_DRAWN * dx
    pick('tag_spacing_mm', lambda r: _uniform(r, max(5.0, tag_lo), max(10.0, tag_lo), 2))

    def draw_size(r):
        lo = math.ceil(FOV_RANGE_MM[0] / dx - 1e-9)
        hi = max(lo, min(math.floor(FOV_RANGE_MM[1] / dx + 1e-9), MAX_DRAWN_SIZE))
        return int(r.integers(lo, hi + 1))

    pick('size', draw_size)
    pick('slice_thickness_mm', lambda r: _uniform(r, 5.0, 10.0, 2))

    _pick_sa_stack(pick, p, fixed)

    pick('la_planes', lambda r: int(r.integers(2, 7)))
    if 'la_angles_deg' in fixed and 'la_planes' not in fixed:
        p['la_planes'] = len(fixed['la_angles_deg'])
    pick('la_angles_deg', lambda r: _draw_la_angles(r, p['la_planes']))
    pick('la_flip', lambda r: [bool(r.random() < 0.5) for _ in range(p['la_planes'])])
    pick('sa_inplane_deg', lambda r: _uniform(r, 0.0, 360.0, 2) % 360.0)
    pick('la_inplane_deg', lambda r: _uniform(r, -30.0, 30.0, 2))
    pick('sa_fov_shift_mm', lambda r: [_uniform(r, -25.0, 25.0, 1) for _ in range(2)])
    pick('la_fov_shift_mm', lambda r: [_uniform(r, -25.0, 25.0, 1) for _ in range(2)])

    pick('num_phases', lambda r: int(r.integers(16, 41)))
    pick('cycle_duration_s', lambda r: _uniform(r, 0.7, 1.2, 3))
    pick('t1_s', lambda r: _uniform(r, 0.8, 1.2, 3))
    pick('snr', lambda r: _uniform(r, 10.0, 40.0, 1))

    if 'background_m0' in fixed and 'background' not in fixed:
        kinds = ('none',) if fixed['background_m0'] == 0.0 else ('untagged', 'tagged')
    else:
        kinds = ('none', 'untagged', 'tagged')
    pick('background', lambda r: kinds[int(r.integers(len(kinds)))])
    bg_range = {'none': (0.0, 0.0), 'untagged': (0.05, 0.2), 'tagged': (0.2, 0.5)}[p['background']]
    pick('background_m0', lambda r: _uniform(r, *bg_range, 3))
    pick('blood_m0', lambda r: _uniform(r, 0.3, 1.3, 3))

    pick('sa_order', lambda r: ('base_first', 'apex_first')[int(r.integers(2))])
    pick('sa_normal', lambda r: ('base_to_apex', 'apex_to_base')[int(r.integers(2))])

    pick('dicom_bits', lambda r: (8, 12, 16)[int(r.integers(3))])
    pick('dicom_rescale', lambda r: bool(r.random() < 0.5))
    pick(
        'dicom_rescale_intercept',
        lambda r: _uniform(r, -0.5, 0.0, 3) + 0.0 if p['dicom_rescale'] else 0.0,
    )
    pick('dicom_range_fill', lambda r: _uniform(r, 0.5, 0.95, 3))
    pick('dicom_sa_series', lambda r: ('per_slice', 'single')[int(r.integers(2))])
    pick('dicom_instance_numbers', lambda r: ('per_slice', 'across_slices')[int(r.integers(2))])
    pick('dicom_file_names', lambda r: ('ordered', 'random')[int(r.integers(2))])
    return validate_protocol({k: p[k] for k in ITEMS})


# --------------------------------------------------------------------------- using one
def _septum_hint(hint, axis, angle_deg: float) -> list[float]:
    """Project ``hint`` ⟂ ``axis`` and turn it by ``angle_deg`` about it (CCW seen from apex)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    h = np.asarray(hint, dtype=np.float64)
    h = h - (h @ a) * a
    e1 = h / np.linalg.norm(h)
    e2 = np.cross(-a, e1)  # θ = +90°, as in the motion's local frame
    t = math.radians(angle_deg)
    return [float(x) for x in math.cos(t) * e1 + math.sin(t) * e2]


def _pick_sa_stack(pick, p: dict, fixed: dict) -> None:
    """
    Draw the SA stack's count, spacing and base gap jointly, so that it fits the LV.

    See :func:`draw_protocol`'s Notes.

    Parameters
    ----------
    pick : callable
        ``pick(name, draw)``: takes the fixed item, else ``draw(rng)``, into ``p``.
    p : dict
        The protocol drawn so far (``shape`` set).
    fixed : dict
        The items taken as given.

    """
    base_min, room = _sa_room(p['shape'])

    def draw_count(r):
        if 'sa_spacing_mm' in fixed:  # fewer slices at a fixed spacing (at least 2)
            fit = int(math.floor(room / fixed['sa_spacing_mm'] + 1e-9)) + 1
            return int(r.integers(6, min(14, fit) + 1)) if fit >= 6 else max(2, fit)
        fit = int(math.floor(room / 6.0 + 1e-9)) + 1
        return int(r.integers(6, min(14, fit) + 1)) if fit >= 6 else 6

    pick('sa_slices', draw_count)

    def draw_spacing(r):
        widest = room / (p['sa_slices'] - 1)  # the spacing that fills the room
        if widest >= 6.0:
            return _uniform(r, 6.0, min(12.0, widest), 2)
        return max(math.floor(widest * 100.0) / 100.0, 1.0)  # a fixed count: tighter spacing

    pick('sa_spacing_mm', draw_spacing)
    slack = room - (p['sa_slices'] - 1) * p['sa_spacing_mm']
    pick(
        'sa_base_gap_mm',
        lambda r: (
            _uniform(r, base_min, base_min + slack, 2)
            if slack >= 0
            else round(max(base_min + 0.5 * slack, 0.0), 2)
        ),
    )


def protocol_preset(protocol: dict) -> dict:
    """
    Return the preset dict that simulates a protocol (see :func:`simulate_study`).

    Parameters
    ----------
    protocol : dict
        A complete or partial protocol (missing items come from the shape's preset, see
        :func:`complete_protocol`).

    Returns
    -------
    dict
        ``config/phantoms/<shape>.yaml`` with the orientation, motion timing and imaging
        overridden (every optional imaging key of :func:`~mlv_ros.core.sim.imaging.plan_slices`
        set), and the complete protocol under ``"protocol"``.

    Raises
    ------
    ValueError
        As :func:`complete_protocol`.

    """
    p = complete_protocol(protocol)
    s = _shape(p['shape'])
    preset = load_preset(s['preset'])  # a fresh, validated copy
    o, m, im = preset['orientation'], preset['motion'], preset['imaging']
    o['long_axis'] = list(p['long_axis'])
    o['base_centre_mm'] = list(p['base_centre_mm'])
    if p['septum_deg']:
        o['septum_hint'] = _septum_hint(o['septum_hint'], p['long_axis'], p['septum_deg'])
    m['num_phases'] = p['num_phases']
    m['cycle_duration_s'] = p['cycle_duration_s']
    if p['right_ventricle']:
        preset['geometry']['rv'] = preset['geometry'].get('rv') or {}
    else:
        preset['geometry'].pop('rv', None)
    if p['abnormal_regions']:
        m['regions'] = [dict(r) for r in p['abnormal_regions']]
    if p['apex_thickening'] is None:
        m.pop('apex_thickening', None)
    else:
        m['apex_thickening'] = p['apex_thickening']
    stack = (p['sa_slices'] - 1) * p['sa_spacing_mm']
    apex_gap = s['length'] - p['sa_base_gap_mm'] - stack
    if abs(apex_gap - s['apex_gap']) < 1e-9:
        apex_gap = s['apex_gap']  # the preset's own stack: its exact numbers, not a rounding off
    im.update(
        {
            'size': p['size'],
            'pixel_spacing_mm': p['pixel_spacing_mm'],
            'slice_thickness_mm': p['slice_thickness_mm'],
            'sa_slices': p['sa_slices'],
            'sa_base_gap_mm': p['sa_base_gap_mm'],
            'sa_apex_gap_mm': apex_gap,
            'la_planes': p['la_planes'],
            'la_angles_deg': list(p['la_angles_deg']),
            'la_flip': list(p['la_flip']),
            'tag_spacing_mm': p['tag_spacing_mm'],
            'tag_angle_deg': p['tag_angle_deg'],
            'tag_lines': 'grid' if p['tag_lines'] == 'grid' else 'single',  # pair: twice
            't1_s': p['t1_s'],
            'background_m0': p['background_m0'],
            'background_tagged': p['background'] == 'tagged',
            'blood_m0': p['blood_m0'],
            'snr': p['snr'],
            'sa_order': p['sa_order'],
            'sa_normal': p['sa_normal'],
            'sa_inplane_deg': p['sa_inplane_deg'],
            'la_inplane_deg': p['la_inplane_deg'],
            'sa_fov_shift_mm': list(p['sa_fov_shift_mm']),
            'la_fov_shift_mm': list(p['la_fov_shift_mm']),
        }
    )
    preset['protocol'] = p
    return load_preset(preset)


def dicom_options(protocol: dict, study=None, names_seed: int = 0) -> dict:
    """
    Keyword arguments of :func:`~mlv_ros.core.io.dicom.write_study_dicom` for a protocol.

    Parameters
    ----------
    protocol : dict
        A complete protocol.
    study : Study, optional
        Needed when ``dicom_range_fill`` is set: the scale puts the study's brightest pixel at
        that fraction of the stored range (RescaleSlope rounded up to 6 significant digits).
    names_seed : int
        Seeds the random file names.

    Returns
    -------
    dict
        ``pixel_scale`` (stored units per intensity unit), ``bits_stored``, ``rescale``,
        ``rescale_intercept``, ``sa_series``, ``instance_numbers``, ``file_names``,
        ``names_seed`` (plain Python values, JSON-serialisable).

    """
    p = validate_protocol(protocol)
    bits, inter, fill = p['dicom_bits'], p['dicom_rescale_intercept'], p['dicom_range_fill']
    if fill is None:
        scale = LEGACY_PIXEL_SCALE
    else:
        if study is None:
            raise ValueError('dicom_options needs the study to scale to dicom_range_fill')
        peak = max(float(np.max(f.image)) for f in study.frames)
        span = max(peak - inter, 1e-6)
        slope = span / (fill * ((1 << bits) - 1))
        e = math.floor(math.log10(slope)) - 5
        slope = math.ceil(slope / 10.0**e) * 10.0**e  # 6 significant digits, rounded up
        scale = 1.0 / slope
    return {
        'pixel_scale': float(scale),
        'bits_stored': int(bits),
        'rescale': bool(p['dicom_rescale']),
        'rescale_intercept': float(inter),
        'sa_series': p['dicom_sa_series'],
        'instance_numbers': p['dicom_instance_numbers'],
        'file_names': p['dicom_file_names'],
        'names_seed': int(names_seed),
    }


def protocol_identity(protocol: dict) -> dict:
    """
    Return the items that name a study (its UIDs): the protocol less line-pair items at default.

    A study drawn before the line-pair items existed keeps its UIDs (and so its files, bit for
    bit): an item at its :data:`PAIR_DEFAULTS` value is left out.

    Parameters
    ----------
    protocol : dict
        A complete protocol.

    Returns
    -------
    dict
        The items, in :data:`ITEMS` order.

    """
    return {k: v for k, v in protocol.items() if k not in PAIR_DEFAULTS or v != PAIR_DEFAULTS[k]}


# --------------------------------------------------------------------------- files
def load_protocol(path) -> dict:
    """
    Read a protocol YAML file (any subset of the items; checked item by item).

    Raises
    ------
    FileNotFoundError
        No such file.
    ValueError
        Not YAML, not a mapping, an unknown item or a value outside its accepted range.

    """
    path = Path(path)
    try:
        with open(path, encoding='utf-8') as fh:
            data = yaml.safe_load(fh)
    except FileNotFoundError:
        raise FileNotFoundError(f'protocol file not found: {path}') from None
    except yaml.YAMLError as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f'protocol file {path} is not valid YAML ({first})') from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ValueError(
            f'protocol file {path} must hold a mapping of items, got {type(data).__name__}'
        )
    return check_items(data)


def save_protocol(protocol: dict, path, header: str = '') -> Path:
    """
    Write a protocol as YAML, one item per line with its meaning as a comment.

    Parameters
    ----------
    protocol : dict
        Items to write (in :data:`ITEMS` order).
    path : str or Path
        Output file.
    header : str
        Comment lines put first (``#`` added).

    Returns
    -------
    Path

    """
    path = Path(path)
    lines = [f'# {h}' if h else '#' for h in header.splitlines()]
    for name, it in ITEMS.items():
        if name in protocol:
            value = yaml.safe_dump(
                [protocol[name]], default_flow_style=True, width=10_000, sort_keys=False
            ).strip()
            lines.append(f'{name}: {value[1:-1]}  # {it.doc}')  # the value without the list's [ ]
    path.write_text('\n'.join(lines) + '\n', encoding='utf-8')
    return path
