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
Per-phase motion metrics of the whole LV: the content of ``MotionMetrics.msg``.

:class:`LVAnalyzer` precomputes everything that depends only on the ED cloud (levels, AHA
segments, cardiac frame vectors, endocardial polygon stack, MLS neighbourhoods, EDV) so a
phase costs a few vectorised passes over the particles; :func:`phase_metrics` is the one-shot
convenience wrapper.

Examples
--------
>>> an = LVAnalyzer(X_ed, frame, levels=10)            # doctest: +SKIP
>>> m = an.phase(x, F=None, phase_index=7, num_phases=20)
>>> m.twist_deg, m.cavity_volume_ml, m.segment_ecc

"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from mlv_ros.core.analysis.findings import (
    FINDING_ARRAY_FIELDS,
    segment_lengths,
    segment_uncertainty,
    UNCERTAINTY_FLOOR,
)
from mlv_ros.core.analysis.frame import (
    as_points,
    cardiac_coordinates,
    LVFrame,
    wall_normal_frame,
)
from mlv_ros.core.analysis.motion import (
    _level_dict,
    CavityModel,
    decompose_displacement,
    LevelBinning,
    torsion,
)
from mlv_ros.core.analysis.strain import (
    aha_segments,
    cardiac_strain,
    green_lagrange,
    MLSNeighbourhood,
    segment_means,
)
from mlv_ros.core.verdict import metrics_verdict
import numpy as np

# MotionMetrics' field groups (conversions.py checks and converts by them): per-level arrays
# share one length L; segment arrays are empty or 17 long.
LEVEL_FIELDS = (
    'level_position',
    'twist_deg',
    'sa_radius_mm',
    'longitudinal_displacement_mm',
    'radial_displacement_mm',
    'circumferential_displacement_mm',
)
SCALAR_FIELDS = (
    'time_fraction',
    'la_radius_mm',
    'torsion_deg_per_cm',
    'cavity_volume_ml',
    'ejection_fraction',
)
SEGMENT_FIELDS = ('segment_err', 'segment_ecc', 'segment_ell')
COUNT_FIELDS = ('level_count', 'segment_count')
# Per-segment uncertainties and findings: 0 or 17 entries, NaN allowed (not measured).
NAN_SEGMENT_FIELDS = (
    'segment_err_unc',
    'segment_ecc_unc',
    'segment_ell_unc',
) + FINDING_ARRAY_FIELDS + ('segment_tag_ecc', 'segment_tag_ecc_unc')
_ARRAY_FIELDS = (
    LEVEL_FIELDS + SEGMENT_FIELDS + COUNT_FIELDS + NAN_SEGMENT_FIELDS + ('segment_class',)
)

#: PhaseMetrics fields MotionMetrics.msg does not carry (none since the findings went in).
NOT_IN_MSG_YET = ()


def _empty() -> np.ndarray:
    return np.zeros(0)


@dataclass
class PhaseMetrics:
    """
    Motion metrics of one phase relative to ED; fields map 1:1 onto MotionMetrics.msg.

    Per-level arrays have one entry per *populated* level, apex → base (empty level bins are
    left out, so their length L' may be below the requested ``levels``). Segment arrays have
    17 entries (AHA order 1…17) or are empty when no strain was available. Sign conventions:
    :mod:`mlv_ros.core.analysis.frame` and :mod:`mlv_ros.core.analysis.motion`.

    Attributes
    ----------
    phase_index, num_phases : int
    time_fraction : float
        Phase time / cycle duration, 0..1.
    level_position : ndarray, shape (L',)
        Level bin centre, 0 apex … 1 base (fraction of the ED long-axis length).
    twist_deg : ndarray, shape (L',)
        Rotation about the long axis relative to ED, degrees, + CCW seen from the apex.
    sa_radius_mm : ndarray, shape (L',)
        Average short-axis radius of the level, mm.
    longitudinal_displacement_mm, radial_displacement_mm, circumferential_displacement_mm : ndarray
        Level means of the displacement components, shape (L',), mm (+ toward base / outward /
        CCW arc).
    la_radius_mm : float
        Apex → particle centroid along the long axis, mm (paper's "LA radius").
    torsion_deg_per_cm : float
        (twist_base − twist_apex) / ED distance of those levels, °/cm.
    cavity_volume_ml : float
    ejection_fraction : float
        (EDV − V)/EDV at this phase (0 at ED; 0 if EDV is not positive).
    segment_err, segment_ecc, segment_ell : ndarray, shape (17,) or (0,)
        Mean Green–Lagrange E_rr, E_cc, E_ll per AHA segment; a segment without particles
        (``segment_count == 0``) holds 0.0. The apex cap (17) is taken in the wall-normal frame
        (:func:`~mlv_ros.core.analysis.frame.wall_normal_frame`): E_rr across its wall, E_cc and
        E_ll (meridional) in it.
    level_count : ndarray of int, shape (L',)
        Particles per level. Not in MotionMetrics.msg (optional; empty when unknown).
    segment_count : ndarray of int, shape (17,) or (0,)
        Particles with a valid strain per segment. Not in MotionMetrics.msg (optional).
    segment_err_unc, segment_ecc_unc, segment_ell_unc : ndarray, shape (17,) or (0,)
        Uncertainty of each segment mean (dimensionless; NaN = too few particles to say),
        :func:`mlv_ros.core.analysis.findings.segment_uncertainty`; empty when unknown.
    segment_origin, segment_origin_confidence : int, float
        Where the AHA segments' circumferential origin came from (``SEGMENT_ORIGIN_*`` of
        :mod:`mlv_ros.core.types`: 0 unknown, 1 anatomical prior, 2 RV detected in the images,
        3 given) and the detection's confidence 0…1; set by the motion analyzer from the
        registered model.
    findings_es_phase, finding_* , segment_class
        The per-segment findings of the cycle so far
        (:meth:`mlv_ros.core.analysis.findings.Findings.message_fields`); −1 / empty until the
        analyzer fills them in.
    verdict : int
        0 ok, 1 degraded, 2 failed: whether this motion is physiologically possible
        (:func:`mlv_ros.core.verdict.metrics_verdict`); the analyzer node merges in the
        solver's data-support verdict.
    verdict_reasons : str
        "; "-separated reasons, empty when ok.
    degraded_segments : tuple of int
        AHA segments (1–17) the verdict is confined to (:attr:`Verdict.confined_to
        <mlv_ros.core.verdict.Verdict.confined_to>`): the solver's sector the tag data no longer
        support, when nothing else degrades the phase; empty: ok, failed or degraded as a whole
        (the findings then inflate every segment, :mod:`mlv_ros.core.analysis.findings`).
    study_id, run_id : str
        The study and run the phase was computed from (the model state's; empty = unknown).
    segment_tag_ecc, segment_tag_ecc_unc : ndarray, shape (17,) or (0,)
        The tag tracks' own circumferential strain per segment at this phase and its uncertainty
        (``ModelState.tag_ecc``; :mod:`mlv_ros.core.analysis.tag_strain`); empty when the
        solver gave none; NaN where a segment has too few tracked edges.

    """

    phase_index: int = 0
    num_phases: int = 0
    time_fraction: float = 0.0
    level_position: np.ndarray = field(default_factory=_empty)
    twist_deg: np.ndarray = field(default_factory=_empty)
    sa_radius_mm: np.ndarray = field(default_factory=_empty)
    longitudinal_displacement_mm: np.ndarray = field(default_factory=_empty)
    radial_displacement_mm: np.ndarray = field(default_factory=_empty)
    circumferential_displacement_mm: np.ndarray = field(default_factory=_empty)
    la_radius_mm: float = 0.0
    torsion_deg_per_cm: float = 0.0
    cavity_volume_ml: float = 0.0
    ejection_fraction: float = 0.0
    segment_err: np.ndarray = field(default_factory=_empty)
    segment_ecc: np.ndarray = field(default_factory=_empty)
    segment_ell: np.ndarray = field(default_factory=_empty)
    level_count: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    segment_count: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    segment_err_unc: np.ndarray = field(default_factory=_empty)
    segment_ecc_unc: np.ndarray = field(default_factory=_empty)
    segment_ell_unc: np.ndarray = field(default_factory=_empty)
    segment_origin: int = 0
    segment_origin_confidence: float = 0.0
    findings_es_phase: int = -1
    finding_peak_err: np.ndarray = field(default_factory=_empty)
    finding_peak_ecc: np.ndarray = field(default_factory=_empty)
    finding_peak_ell: np.ndarray = field(default_factory=_empty)
    finding_peak_err_unc: np.ndarray = field(default_factory=_empty)
    finding_peak_ecc_unc: np.ndarray = field(default_factory=_empty)
    finding_peak_ell_unc: np.ndarray = field(default_factory=_empty)
    finding_es_err: np.ndarray = field(default_factory=_empty)
    finding_es_ecc: np.ndarray = field(default_factory=_empty)
    finding_es_ell: np.ndarray = field(default_factory=_empty)
    finding_es_err_unc: np.ndarray = field(default_factory=_empty)
    finding_es_ecc_unc: np.ndarray = field(default_factory=_empty)
    finding_es_ell_unc: np.ndarray = field(default_factory=_empty)
    finding_function_index: np.ndarray = field(default_factory=_empty)
    finding_function_unc: np.ndarray = field(default_factory=_empty)
    segment_class: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    verdict: int = 0
    verdict_reasons: str = ''
    degraded_segments: tuple = ()
    study_id: str = ''
    run_id: str = ''
    segment_tag_ecc: np.ndarray = field(default_factory=_empty)
    segment_tag_ecc_unc: np.ndarray = field(default_factory=_empty)

    def __post_init__(self):
        for name in _ARRAY_FIELDS:
            dt = np.int64 if name.endswith('count') or name == 'segment_class' else np.float64
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=dt).reshape(-1))

    @property
    def has_strain(self) -> bool:
        """Return True when the three segment arrays hold 17 values each."""
        return all(getattr(self, f).size == 17 for f in SEGMENT_FIELDS)

    def to_dict(self) -> dict:
        """JSON-friendly dict (arrays as lists); inverse of :meth:`from_dict`."""
        d = asdict(self)
        for k in _ARRAY_FIELDS:
            d[k] = np.asarray(d[k]).tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> 'PhaseMetrics':
        """
        Build from a dict (e.g. a converted MotionMetrics message).

        Unknown keys are ignored, missing ones take their defaults.
        """
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})


class LVAnalyzer:
    """
    Per-run analysis state built from the ED cloud; call :meth:`phase` per phase.

    Parameters
    ----------
    X_ed : array_like, shape (N, 3)
        ED particle positions, mm (row i = particle i at every phase).
    frame : LVFrame
        ED long-axis frame.
    levels : int
        Equal level bins on [0, 1], apex → base (default 10).
    endo_mask : array_like of bool, shape (N,), optional
        Endocardial particles for the cavity volume (default: innermost per sector).
    volume_slabs, angle_bins : int
        Cavity polygon stack resolution (:class:`~mlv_ros.core.analysis.motion.CavityModel`).
    estimate_strain : bool
        When :meth:`phase` gets no F, estimate it by MLS from positions (default True).
        If False and no F is given, the segment arrays are empty.
    mls_k : int
        Neighbours of the MLS estimate.
    apex_cap : float
        AHA apex-cap level (segment 17).
    edv_ml : float, optional
        End-diastolic volume for the ejection fraction; default the cavity volume of X_ed.

    """

    def __init__(
        self,
        X_ed,
        frame: LVFrame,
        *,
        levels: int = 10,
        endo_mask=None,
        volume_slabs: int = 20,
        angle_bins: int = 36,
        estimate_strain: bool = True,
        mls_k: int = 12,
        apex_cap: float = 0.1,
        edv_ml: float | None = None,
    ):
        if not isinstance(frame, LVFrame):
            raise ValueError(f'frame must be an LVFrame, got {type(frame).__name__}')
        self.X = as_points(X_ed, 'X_ed')
        self.frame = frame
        self.levels = LevelBinning(self.X, frame, levels)
        self.coords = cardiac_coordinates(self.X, frame, levels=int(levels))
        self.segments = aha_segments(
            self.coords.h, self.coords.theta, frame.aha_origin_deg, apex_cap
        )
        self.cavity = CavityModel(self.X, frame, endo_mask, volume_slabs, angle_bins)
        self.estimate_strain = bool(estimate_strain)
        self.mls_k = int(mls_k)
        self._mls: MLSNeighbourhood | None = None
        self.edv_ml = self.cavity.volume_ml(self.X) if edv_ml is None else float(edv_ml)
        self.segment_lengths = segment_lengths(self.coords.rho, self.coords.axial, self.segments)
        # The apex cap's strain in the wall-normal frame (findings: its wall is across the axis).
        cap = self.segments == 17
        e_n, _, e_m = wall_normal_frame(self.coords, frame.length)
        c = self.coords
        self.segment_frame = tuple(v.copy() for v in (c.e_r, c.e_c, c.e_l))
        self.segment_frame[0][cap] = e_n[cap]
        self.segment_frame[2][cap] = e_m[cap]

    @property
    def mls(self) -> MLSNeighbourhood:
        """MLS neighbourhoods of X_ed (built on first use)."""
        if self._mls is None:
            self._mls = MLSNeighbourhood(self.X, self.mls_k)
        return self._mls

    def strain(self, x: np.ndarray, F=None, *, segment_frame: bool = False) -> dict | None:
        """
        Return the cardiac strain components per particle (dict of (N,) arrays).

        Parameters
        ----------
        x : array_like, shape (N, 3)
            Current positions, mm.
        F : array_like, shape (N, 3, 3), optional
            Deformation gradients; default the MLS estimate from ``x``.
        segment_frame : bool
            False (default): the cylindrical radial / circumferential / longitudinal frame
            everywhere. True: the frame the segment means use, the same except in the apex cap
            (segment 17), where ``rr`` is the wall-normal strain (thickening) and ``ll`` the
            meridional in-wall strain (:func:`~mlv_ros.core.analysis.frame.wall_normal_frame`).

        Returns
        -------
        dict or None
            Keys ``rr, cc, ll, rc, rl, cl``; None when no F is given and estimation is off.

        """
        if F is None:
            if not self.estimate_strain:
                return None
            F = self.mls.gradient(x)
        else:
            F = np.asarray(F, dtype=np.float64)
            if F.shape != (self.X.shape[0], 3, 3):
                raise ValueError(f'F must have shape ({self.X.shape[0]}, 3, 3), got {F.shape}')
        c = self.coords
        e = self.segment_frame if segment_frame else (c.e_r, c.e_c, c.e_l)
        return cardiac_strain(green_lagrange(F), *e)

    def phase(
        self,
        x,
        F=None,
        *,
        phase_index: int = 0,
        num_phases: int = 0,
        time_fraction: float | None = None,
        apex=None,
        residual_mm: float = 0.0,
    ) -> PhaseMetrics:
        """
        Metrics of one phase.

        Parameters
        ----------
        x : array_like, shape (N, 3)
            Current positions, mm, same particle order as X_ed.
        F : array_like, shape (N, 3, 3), optional
            Deformation gradients ∂x/∂X relative to ED (e.g. the meshless model's MLS
            gradient); NaN rows are skipped in the segment means.
        phase_index, num_phases : int
            Index of this phase in the cycle (0 = ED) and number of phases in the cycle.
        time_fraction : float, optional
            Default ``phase_index / num_phases`` (0 when num_phases is 0).
        apex : array_like, shape (3,), optional
            Current apex for the LA radius (default: the ED apex).
        residual_mm : float
            The solver's RMS residual at the control points for this phase, mm
            (``ModelState.residual``; 0 = unknown): enters the segment uncertainties
            (:mod:`mlv_ros.core.analysis.findings`).

        Returns
        -------
        PhaseMetrics

        """
        x = as_points(x, 'x')
        if x.shape != self.X.shape:
            raise ValueError(f'x must have shape {self.X.shape} like X_ed, got {x.shape}')
        lv = _level_dict(self.levels, decompose_displacement(self.X, x, self.frame), x)
        vol = self.cavity.volume_ml(x)
        ef = (self.edv_ml - vol) / self.edv_ml if self.edv_ml > 0 else 0.0
        if time_fraction is None:
            time_fraction = phase_index / num_phases if num_phases > 0 else 0.0
        ap = self.frame.apex if apex is None else np.asarray(apex, dtype=np.float64).reshape(3)
        seg = {}
        st = self.strain(x, F, segment_frame=True)
        if st is not None:
            for key, comp in (('segment_err', 'rr'), ('segment_ecc', 'cc'), ('segment_ell', 'll')):
                seg[key], seg['segment_count'] = segment_means(st[comp], self.segments)
                seg[f'{key}_unc'] = segment_uncertainty(
                    st[comp],
                    self.segments,
                    seg['segment_count'],
                    UNCERTAINTY_FLOOR[key[-3:]],
                    self.segment_lengths[key[-3:]],
                    residual_mm if np.isfinite(residual_mm) else 0.0,
                    self.mls_k,
                )
        verdict = metrics_verdict(
            ef,
            float(np.max(np.linalg.norm(x - self.X, axis=1))),
            self.frame.length,
            [seg.get(k, ()) for k in ('segment_err', 'segment_ecc', 'segment_ell')],
            edv_ml=self.edv_ml,
        )
        return PhaseMetrics(
            verdict=verdict.level,
            verdict_reasons=verdict.text,
            phase_index=int(phase_index),
            num_phases=int(num_phases),
            time_fraction=float(time_fraction),
            level_position=lv['level_position'],
            twist_deg=lv['twist_deg'],
            sa_radius_mm=lv['sa_radius_mm'],
            longitudinal_displacement_mm=lv['longitudinal_displacement_mm'],
            radial_displacement_mm=lv['radial_displacement_mm'],
            circumferential_displacement_mm=lv['circumferential_displacement_mm'],
            la_radius_mm=float((x.mean(axis=0) - ap) @ self.frame.axis),
            torsion_deg_per_cm=torsion(lv['twist_deg'], lv['axial_ed_mm']),
            cavity_volume_ml=vol,
            ejection_fraction=float(ef),
            level_count=lv['count'],
            **seg,
        )


def phase_metrics(X_ed, x, frame: LVFrame, F=None, levels: int = 10, **kwargs) -> PhaseMetrics:
    """
    One-shot :class:`PhaseMetrics` of positions ``x`` relative to ``X_ed``.

    Builds an :class:`LVAnalyzer` (keyword arguments are passed on, plus ``phase_index``,
    ``num_phases``, ``time_fraction`` and ``apex`` to :meth:`LVAnalyzer.phase`). For a whole
    cycle build the analyzer once instead: the ED precomputation dominates the cost.
    """
    phase_kw = {
        k: kwargs.pop(k)
        for k in ('phase_index', 'num_phases', 'time_fraction', 'apex')
        if k in kwargs
    }
    return LVAnalyzer(X_ed, frame, levels=levels, **kwargs).phase(x, F, **phase_kw)
