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
A segment's own tag evidence: circumferential strain of its short-axis tag tracks.

The model's strain is a smoothed field: a narrow region moving unlike its neighbours is carried
along with them by the elastic and incompressibility penalties, and then reads normal. The tag
points themselves are the data. On each short-axis (SA) slice the tracked tag intersections are
material points of the wall; classic tag analysis reads the 2-D Lagrangian strain between them,
ED → phase, with no model (the segment lengths between tag intersections of Moore et al.,
Radiology 2000; Götte et al., JACC 2001).

Per SA slice (:func:`slice_tag_edges`, once at ED; :class:`TagEdges`): every pair of the
slice's tracks at most :data:`MAX_EDGE_SPACINGS` × the slice's own grid spacing apart at ED
(the median ED nearest-neighbour distance of its tracks: one tag period λ on a grid), both
tracked at the phase, is an edge. A grid's neighbours are λ and λ√2 apart, so an edge never
spans the cavity, a gap of lost tracks or the outside of the wall, whatever the study's period
or pixel size. Its Green–Lagrange strain along its ED direction ``t`` is exact for any
deformation homogeneous over the edge::

    e = (|dx|² − |dX|²) / (2 |dX|²) = tᵀ E t = c² Ecc + s² Err + 2 c s Ecr

with ``c``, ``s`` the components of ``t`` along the circumferential and radial directions (about
the LV long axis, at the edge's ED midpoint, in the image plane). A wall one or two tags thick
holds a ring of tracks whose edges mostly run circumferentially; where they run at an angle, the
Err term (+0.2…0.5 at ES) would bias an edge read as Ecc, so the three components are fitted.

Per AHA segment (:func:`segment_tag_strain`), the edges of its segment (their ED midpoint's,
:func:`~mlv_ros.core.analysis.strain.aha_segments` of the LV frame) over every SA slice: weighted
least squares of (Ecc, Err, Ecr), each edge weighted by its localisation-noise variance
``(2 σ_loc / ℓ)²`` (both ends σ_loc-noisy in two axes; σ_loc mm per axis, the solver's measured
noise of the slice, :data:`DEFAULT_NOISE_MM` where not yet measured; ℓ the ED edge length). Its
Ecc and uncertainty::

    σ² = FLOOR² + cov_cc × max(1, χ²/dof)

``FLOOR`` the readers' spread (:data:`TAG_ECC_FLOOR`, as the model's findings), ``cov_cc`` the
fit's Ecc variance from the noise (it falls with the number of edges and grows when their
directions cannot tell Ecc from Err), scaled up by the reduced χ² when the edges scatter more
than the noise explains (a segment across a hinge, a slipped track). A segment with fewer than
:data:`MIN_EDGES` edges, or whose edge directions cannot separate Ecc from Err, has no tag
evidence (NaN).

This is the data's own reading of regional contraction;
:func:`mlv_ros.core.analysis.findings.classify` uses it where it disagrees with the model's.
"""

from __future__ import annotations

from mlv_ros.core.analysis.strain import aha_segments
import numpy as np

#: Longest edge, in units of the slice's grid spacing (median ED nearest-neighbour distance of
#: its tracks). A grid's neighbours are 1 and √2 ≈ 1.41 apart; 1.6 leaves room for a grid
#: sheared by the wall's curvature and the tracks' noise, and is below 2 (across a lost track).
MAX_EDGE_SPACINGS = 1.6
#: Fewer edges than this in a segment: no tag evidence (the fit has three unknowns).
MIN_EDGES = 5
#: Smallest uncertainty of a segment's tag Ecc: the spread between experienced readers of tagged
#: MRI (as :data:`mlv_ros.core.analysis.findings.UNCERTAINTY_FLOOR`'s Ecc).
TAG_ECC_FLOOR = 0.02
#: Localisation noise (mm per in-plane axis) assumed where the solver has not measured it: the
#: tracker's noise on the presets (0.09–0.16 mm by slice, the solver's ``tag_noise_mm``).
DEFAULT_NOISE_MM = 0.15
#: Largest condition number of the (Ecc, Err, Ecr) normal equations: beyond it the segment's
#: edge directions do not separate the components.
MAX_CONDITION = 1e8


def _plane_basis(normal) -> tuple[np.ndarray, np.ndarray]:
    """Return two unit in-plane axes (3,) each, orthogonal to ``normal``."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def slice_tag_edges(ed, normal, axis_point, axis_dir, spacing_mm: float | None = None) -> dict:
    """
    Return one SA slice's tag-track edges at ED (module docstring): who, how long, which way.

    Parameters
    ----------
    ed : array_like, shape (K, 3)
        ED positions of the slice's tracks, mm (patient; in the image plane).
    normal : array_like, shape (3,)
        The image plane's normal.
    axis_point, axis_dir : array_like, shape (3,)
        A point of the LV long axis (mm) and its direction (apex → base).
    spacing_mm : float, optional
        The grid spacing edges are measured against; default the median ED nearest-neighbour
        distance of the tracks.

    Returns
    -------
    dict
        ``i``, ``j`` (M,) the tracks (rows of ``ed``) each edge joins; ``midpoint`` (M, 3) ED
        midpoints, mm; ``length`` (M,) ED length, mm; ``cos``, ``sin`` (M,) the ED direction's
        components along e_θ and e_r at the midpoint (in the plane). Empty (M = 0) when fewer
        than 2 tracks.

    Raises
    ------
    ValueError
        Non-finite ED positions or a zero normal / axis.

    """
    ed = np.asarray(ed, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(ed).all():
        raise ValueError('ED tag positions must be finite')
    axis = np.asarray(axis_dir, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    if not (np.linalg.norm(axis) > 0 and np.linalg.norm(n) > 0):
        raise ValueError('normal and axis_dir must be non-zero vectors')
    axis = axis / np.linalg.norm(axis)
    if len(ed) < 2:
        z = np.zeros(0)
        return {'i': z.astype(np.int64), 'j': z.astype(np.int64), 'midpoint': np.zeros((0, 3)),
                'length': z, 'cos': z, 'sin': z}
    u, v = _plane_basis(n)
    P = np.stack([ed @ u, ed @ v], axis=1)
    d = np.sqrt(np.sum((P[:, None] - P[None]) ** 2, axis=2))
    np.fill_diagonal(d, np.inf)
    if spacing_mm is None:
        spacing_mm = float(np.median(d.min(axis=1)))
    i, j = np.nonzero(np.triu(d <= MAX_EDGE_SPACINGS * spacing_mm, 1) & (d > 0))
    dX = P[j] - P[i]
    length = np.sqrt(np.sum(dX**2, axis=1))
    mid = 0.5 * (ed[i] + ed[j])
    r = mid - np.asarray(axis_point, dtype=np.float64)
    r = r - (r @ axis)[:, None] * axis
    e_r = np.stack([r @ u, r @ v], axis=1)
    e_r /= np.maximum(np.sqrt(np.sum(e_r**2, axis=1, keepdims=True)), 1e-12)
    e_t = np.stack([-e_r[:, 1], e_r[:, 0]], axis=1)  # (u × v) × e_r in the plane
    if np.dot(np.cross(u, v), axis) < 0:  # e_θ = axis × e_r
        e_t = -e_t
    t = dX / np.maximum(length, 1e-12)[:, None]
    return {
        'i': i,
        'j': j,
        'midpoint': mid,
        'length': length,
        'cos': np.sum(t * e_t, axis=1),
        'sin': np.sum(t * e_r, axis=1),
    }


class TagEdges:
    """
    The SA slices' tag-track edges of a study at ED, read at any phase (module docstring).

    Built once from the ED tracks (what does not change from phase to phase: which tracks are
    neighbours, their ED lengths and directions, their segments); :meth:`segment_strain` then
    reads a phase from the tracks' positions there.

    Parameters
    ----------
    slices : iterable of tuple
        Per SA slice ``(ed, normal)``: ED track positions (K, 3), mm, and the plane's normal.
    frame : LVFrame
        The LV frame at ED (the analysis' own: its axis, levels and AHA origin).

    """

    def __init__(self, slices, frame):
        starts, parts, offset = [], [], 0
        for k, (ed, normal) in enumerate(slices):
            ed = np.asarray(ed, dtype=np.float64).reshape(-1, 3)
            e = slice_tag_edges(ed, normal, frame.apex, frame.axis)
            e['i'], e['j'] = e['i'] + offset, e['j'] + offset
            e['slice'] = np.full(len(e['i']), k, dtype=np.int64)
            parts.append(e)
            starts.append(offset)
            offset += len(ed)
        self.num_tracks = offset
        keys = ('i', 'j', 'midpoint', 'length', 'cos', 'sin', 'slice')
        if parts:
            e = {n: np.concatenate([p[n] for p in parts]) for n in keys}
        else:
            e = slice_tag_edges(np.zeros((0, 3)), (0, 0, 1), frame.apex, frame.axis)
            e['slice'] = np.zeros(0, dtype=np.int64)
        self.i, self.j, self.length = e['i'], e['j'], e['length']
        self.cos, self.sin, self.slice = e['cos'], e['sin'], e['slice']
        self.num_slices = len(starts)
        mid = e['midpoint']
        if len(mid):
            ie = frame.inplane(mid)
            self.segment = aha_segments(
                np.clip(frame.level(mid), 0.0, 1.0),
                np.arctan2(ie[:, 1], ie[:, 0]),
                frame.aha_origin_deg,
            )
        else:
            self.segment = np.zeros(0, dtype=np.int64)
        self._design = np.stack([self.cos**2, self.sin**2, 2.0 * self.cos * self.sin], axis=1)

    def segment_strain(self, now, noise_mm=None) -> dict:
        """
        Return each AHA segment's tag Ecc at a phase, its uncertainty and its edge count.

        Parameters
        ----------
        now : array_like, shape (num_tracks, 3)
            The tracks' positions at the phase, mm, in the order of the slices' ED tracks
            (NaN rows: not tracked at the phase).
        noise_mm : array_like, shape (num_slices,), optional
            Each slice's localisation noise σ_loc, mm per axis (NaN or missing:
            :data:`DEFAULT_NOISE_MM`).

        Returns
        -------
        dict
            ``ecc``, ``ecc_unc`` shape (17,) (NaN: no evidence) and ``edges`` shape (17,) int
            (edges tracked at the phase).

        Raises
        ------
        ValueError
            ``now`` of another shape.

        """
        x = np.asarray(now, dtype=np.float64).reshape(-1, 3)
        if x.shape[0] != self.num_tracks:
            raise ValueError(f'now must hold {self.num_tracks} track positions, got {x.shape[0]}')
        sig = np.full(self.num_slices, DEFAULT_NOISE_MM)
        if noise_mm is not None:
            given = np.asarray(noise_mm, dtype=np.float64).reshape(-1)
            sig = np.where(np.isfinite(given) & (given > 0), given, sig)
        dx = x[self.j] - x[self.i]
        live = np.isfinite(dx).all(axis=1)
        strain = (np.sum(dx**2, axis=1) - self.length**2) / (2.0 * self.length**2)
        out = {
            'ecc': np.full(17, np.nan),
            'ecc_unc': np.full(17, np.nan),
            'edges': np.zeros(17, dtype=np.int64),
        }
        if not live.any():
            return out
        w = np.where(live, (self.length / (2.0 * sig[self.slice])) ** 2, 0.0)
        strain = np.where(live, strain, 0.0)
        seg = self.segment - 1
        out['edges'] = np.bincount(seg[live], minlength=17)[:17].astype(np.int64)
        # Each segment's weighted normal equations N x = b, x = (Ecc, Err, Ecr), at once.
        A = self._design
        N = np.empty((17, 3, 3))
        for p in range(3):
            for q in range(p, 3):
                N[:, p, q] = N[:, q, p] = np.bincount(
                    seg, weights=w * A[:, p] * A[:, q], minlength=17
                )[:17]
        b = np.stack(
            [np.bincount(seg, weights=w * strain * A[:, p], minlength=17)[:17] for p in range(3)],
            axis=1,
        )
        ee = np.bincount(seg, weights=w * strain**2, minlength=17)[:17]
        fit = out['edges'] >= MIN_EDGES
        fit[fit] = np.linalg.cond(N[fit]) <= MAX_CONDITION
        if not fit.any():
            return out
        cov = np.linalg.inv(N[fit])
        x = np.einsum('kab,kb->ka', cov, b[fit])
        # Weighted residual sum of squares: eᵀWe − 2 xᵀb + xᵀNx = eᵀWe − xᵀb at the solution.
        rss = np.maximum(ee[fit] - np.sum(x * b[fit], axis=1), 0.0)
        dof = out['edges'][fit] - 3
        chi2 = np.where(dof > 0, rss / np.maximum(dof, 1), 1.0)
        var = cov[:, 0, 0] * np.maximum(chi2, 1.0)
        out['ecc'][fit] = x[:, 0]
        out['ecc_unc'][fit] = np.sqrt(TAG_ECC_FLOOR**2 + var)
        return out


def segment_tag_strain(slices, frame, noise_mm=None) -> dict:
    """
    Return each AHA segment's tag Ecc, its uncertainty and its edge count (module docstring).

    One phase at once (:class:`TagEdges` reads many phases of the same ED tracks).

    Parameters
    ----------
    slices : iterable of tuple
        Per SA slice ``(ed, now, normal)``: ED positions (K, 3), the same tracks' positions at
        the phase (K, 3; NaN rows: not tracked), mm, and the plane's normal; optionally a fourth
        item, the slice's localisation noise σ_loc (mm per axis; None: unknown).
    frame : LVFrame
        The LV frame at ED.
    noise_mm : float, optional
        σ_loc of slices that give none (default :data:`DEFAULT_NOISE_MM`).

    Returns
    -------
    dict
        As :meth:`TagEdges.segment_strain`.

    Raises
    ------
    ValueError
        ``ed`` and ``now`` of a slice of different shapes.

    """
    slices = list(slices)
    for ed, now, *_ in slices:
        if np.shape(ed) != np.shape(now):
            raise ValueError(
                f'ed and now must have the same shape, got {np.shape(ed)} and {np.shape(now)}'
            )
    edges = TagEdges([(ed, normal) for ed, _, normal, *_ in slices], frame)
    default = DEFAULT_NOISE_MM if noise_mm is None else float(noise_mm)
    sig = [
        default if len(item) < 4 or item[3] is None else float(item[3]) for item in slices
    ]
    now = np.concatenate([np.asarray(n, dtype=np.float64).reshape(-1, 3) for _, n, *_ in slices])
    return edges.segment_strain(now if slices else np.zeros((0, 3)), sig if slices else None)
