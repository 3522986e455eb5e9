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
Plain data records that flow through the pipeline.

Pure numpy; the conversion module maps each to its ROS message.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mlv_ros.core.geometry import SliceGeometry
import numpy as np

VIEW_SA = 0
VIEW_LA = 1
#: ``Frame.tag_lines``: a tag grid (or not known); one family of parallel tag lines in ``image``;
#: two single-line series of the slice, one family in ``image`` and the other in ``line_image``.
TAGS_GRID = 0
TAGS_LINES = 1
TAGS_LINE_PAIR = 2
#: Begins the part of a line pair's ED ``TagPointSet.status`` that says its two series (two
#: breath-holds) disagree beyond what was corrected; the solver degrades every phase for it.
PAIR_MISREGISTERED = 'line pair misregistered'
VIEW_NAMES = {VIEW_SA: 'SA', VIEW_LA: 'LA'}


@dataclass
class Frame:
    """
    One tagged cine image (one slice at one phase).

    Attributes
    ----------
    image : ndarray, shape (rows, cols)
        Pixel values: uint16 (scanner units) or float32.
    geometry : SliceGeometry
        Plane in patient coordinates.
    view : int
        ``VIEW_SA`` or ``VIEW_LA``.
    slice_index : int
        Index within its view (SA: 0 = most basal).
    phase_index, num_phases : int
        Cardiac phase (0 = end-diastole) and phases per cycle.
    trigger_time : float
        Seconds after the R wave.
    cycle_duration : float
        RR interval, s (0 if unknown).
    series_uid : str
        DICOM SeriesInstanceUID of the slice's cine (or a synthetic id).
    num_sa_slices, num_la_slices : int
        Slices per view in the whole acquisition (0 = unknown); lets a consumer tell when all
        slices of a phase have arrived.
    study_id : str
        The study the frame belongs to (DICOM StudyInstanceUID or a hash; empty = unknown): a
        consumer keeps to one study (:class:`StudyShape`).
    run_id : str
        The run that published it (a nonce drawn once by the frame source; empty = unknown):
        two runs of one study differ in it, and a consumer keeps to one run too.
    tag_lines : int
        ``TAGS_GRID`` (a tag grid, or not known), ``TAGS_LINES`` (``image`` shows one family of
        parallel tag lines, single-line SPAMM) or ``TAGS_LINE_PAIR`` (two single-line series
        of this slice, acquired apart at the same position, orientation and phases: one family
        in ``image``, the other in ``line_image``).
    line_image : ndarray or None
        ``TAGS_LINE_PAIR``: the second series' image at this phase, same shape and dtype as
        ``image``; None otherwise.

    """

    image: np.ndarray
    geometry: SliceGeometry
    view: int
    slice_index: int
    phase_index: int
    num_phases: int
    trigger_time: float = 0.0
    cycle_duration: float = 0.0
    series_uid: str = ''
    num_sa_slices: int = 0
    num_la_slices: int = 0
    study_id: str = ''
    run_id: str = ''
    tag_lines: int = TAGS_GRID
    line_image: np.ndarray | None = None


@dataclass
class TagPointSet:
    """
    Tag intersections of one frame.

    Attributes
    ----------
    pixel_rc : ndarray, shape (N, 2)
        (row, column), pixels, sub-pixel.
    position : ndarray, shape (N, 3)
        Patient coordinates, mm (LPS).
    track_id : ndarray of int32, shape (N,)
        Stable through the slice's cine, assigned at ED; -1 = untracked.
    confidence : ndarray of float32, shape (N,)
        0..1.
    status : str
        Empty when fine; otherwise why the set is empty or partial.
    study_id, run_id : str
        As in the source :class:`Frame`.
    line_normal : ndarray, shape (N, 3) or (0, 3)
        Points on a single family of tag lines (no intersections): each point's tag-line
        normal, a unit vector in the image plane (patient coordinates), along which alone the
        point measures motion (a row of NaN: that point is an intersection). Empty (the
        default): every point is a grid intersection and measures its in-plane motion.

    """

    view: int
    slice_index: int
    phase_index: int
    num_phases: int
    geometry: SliceGeometry
    pixel_rc: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    position: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    track_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    status: str = ''
    stamp: float = 0.0  # s, copied from the source frame's header
    num_sa_slices: int = 0  # as in Frame
    num_la_slices: int = 0
    study_id: str = ''  # as in Frame
    run_id: str = ''  # as in Frame
    line_normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def __len__(self) -> int:
        return int(self.track_id.shape[0])


@dataclass
class ModelState:
    """
    Global parameters of the meshless deformable model at one phase (paper eq. 1–3).

    ``x = c + R p``, ``p = s + d``; ``rotation`` is the unit quaternion (w, x, y, z) of R
    (model-centred → patient); ``translation`` is c in mm; ``a0`` mm; ``a1..a3`` and ``tau``
    dimensionless (twist φ = π τ sin α). ``verdict`` (0 ok, 1 degraded, 2 failed) and
    ``verdict_reasons`` ("; "-separated) say how far the data supported this phase
    (:mod:`mlv_ros.core.verdict`). ``study_id`` and ``run_id`` name the study and run the state
    was computed from (as in :class:`Frame`). ``segment_origin`` (:data:`SEGMENT_ORIGIN_CODES`)
    and ``segment_origin_confidence`` (0…1) say where the registered model's circumferential
    reference came from (0 / 0.0 on per-phase states). ``degraded_segments``: the AHA segments
    (1–17, ascending) a degraded verdict is confined to (:attr:`Verdict.confined_to
    <mlv_ros.core.verdict.Verdict.confined_to>`: a sector the tag data no longer support); empty
    when the verdict is ok, failed or degraded for a whole-heart reason. ``tag_ecc`` /
    ``tag_ecc_unc``: the tag tracks' own circumferential strain per AHA segment at this phase and
    its uncertainty (:func:`mlv_ros.core.analysis.tag_strain.segment_tag_strain`), shape (17,) or
    empty (not computed); NaN where a segment has too few tracked edges.
    """

    phase_index: int = 0
    num_phases: int = 0
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    a0: float = 1.0
    a1: float = 1.0
    a2: float = 1.0
    a3: float = 1.0
    tau: float = 0.0
    iterations: int = 0
    residual: float = 0.0
    converged: bool = False
    num_particles: int = 0
    num_control_points: int = 0
    verdict: int = 0
    verdict_reasons: str = ''
    study_id: str = ''
    run_id: str = ''
    segment_origin: int = 0
    segment_origin_confidence: float = 0.0
    degraded_segments: tuple = ()
    tag_ecc: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tag_ecc_unc: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass
class RegisteredModel:
    """
    The registered ED model as the graph hands it on: particles, their model coordinates, state.

    The registration publishes it (paper §3.2) as a point cloud and a model state of the same
    header stamp; the solver rebuilds exactly the same model from it and the analyzer measures
    against it.

    Attributes
    ----------
    positions : ndarray, shape (N, 3)
        Particle positions at ED, mm (patient, LPS).
    alpha, beta : ndarray, shape (N,)
        Polar model coordinates of each particle (paper eq. 1), rad: α latitude (−π/2 at the
        apex), β longitude (0 at the reference direction).
    w : ndarray, shape (N,)
        Radial model coordinate, ``|p| / a0`` (dimensionless).
    state : ModelState
        The global parameters at ED (its ``study_id`` names the study).
    transmural : ndarray, shape (N,), optional
        Transmural depth, 0 endocardium → 1 epicardium (None when not given).

    """

    positions: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray
    w: np.ndarray
    state: ModelState
    transmural: np.ndarray | None = None

    @property
    def polar(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the polar model coordinates (α, β, w), as :class:`MotionTracker` takes them."""
        return self.alpha, self.beta, self.w

    def __len__(self) -> int:
        return int(self.positions.shape[0])


#: ModelState / MotionMetrics ``segment_origin`` codes: where the circumferential reference (and
#: so the AHA segments) came from (mlv_ros/core/registration/anatomy.py).
SEGMENT_ORIGIN_CODES = {'unknown': 0, 'prior': 1, 'detected': 2, 'given': 3}


class ForeignStudyError(ValueError):
    """A message of another study than the one a consumer keeps to (see :class:`StudyShape`)."""

    def __init__(self, study_id: str, foreign: str):
        self.study_id, self.foreign = study_id, foreign
        super().__init__(f"of another study: {foreign!r} (this node's study: {study_id!r})")


@dataclass
class StudyShape:
    """
    An acquisition's identity and dimensions as its messages declare them.

    Every message must agree.

    ``study_id``, ``run_id`` and each dimension are taken from the first message that declares
    them (empty ids and slice counts of 0 mean unknown); a later message of another study, or of
    another run of the same study, is foreign (:class:`ForeignStudyError`: a second graph on the
    same ROS domain, to be reported and ignored), and one declaring a different dimension
    contradicts the study and is refused, so one corrupt message cannot make a consumer wait for
    phases or slices that do not exist.
    """

    num_phases: int = 0
    num_sa_slices: int = 0
    num_la_slices: int = 0
    study_id: str = ''
    run_id: str = ''

    @property
    def label(self) -> str:
        """Return the study (and run) kept to, for people: ``study`` or ``study run R``."""
        return f'{self.study_id} run {self.run_id}' if self.run_id else self.study_id

    def other(self, study_id: str, run_id: str = '') -> str | None:
        """
        Name what makes ``study_id`` / ``run_id`` foreign (for people); None for this node's own.

        ``study_id`` for another study, ``'<study_id> run <run_id>'`` for another run of this one.
        An unknown id, on either side, is never foreign.
        """
        if self.study_id and study_id and study_id != self.study_id:
            return study_id
        if self.run_id and run_id and run_id != self.run_id:
            return f'{study_id or self.study_id} run {run_id}'
        return None

    def foreign(self, study_id: str, run_id: str = '') -> bool:
        """Whether ``study_id`` / ``run_id`` name another study or run than the ones adopted."""
        return self.other(study_id, run_id) is not None

    def adopt(self, study_id: str, run_id: str = '') -> None:
        """
        Keep to ``study_id`` and ``run_id`` from now on (each when none is known yet).

        Raises
        ------
        ForeignStudyError
            Another study or run is already adopted.

        """
        other = self.other(study_id, run_id)
        if other is not None:
            raise ForeignStudyError(self.label, other)
        self.study_id = self.study_id or str(study_id or '')
        self.run_id = self.run_id or str(run_id or '')

    def check(self, item) -> None:
        """
        Adopt or verify the study, run and dimensions of ``item``.

        ``item`` is a :class:`Frame` or :class:`TagPointSet`; any object with these attributes,
        missing ones unknown.

        Raises
        ------
        ForeignStudyError
            ``item`` belongs to another study or run (checked first).
        ValueError
            ``item`` declares a dimension different from the one already known.

        """
        study_id, run_id = getattr(item, 'study_id', ''), getattr(item, 'run_id', '')
        other = self.other(study_id, run_id)
        if other is not None:
            raise ForeignStudyError(self.label, other)
        names = ('num_phases', 'num_sa_slices', 'num_la_slices')
        clash = [
            f'{name} {getattr(item, name, 0)} (study: {getattr(self, name)})'
            for name in names
            if getattr(self, name)
            and getattr(item, name, 0)
            and getattr(item, name, 0) != getattr(self, name)
        ]
        if clash:
            raise ValueError('inconsistent with the study: ' + ', '.join(clash))
        for name in names:
            setattr(self, name, getattr(self, name) or int(getattr(item, name, 0)))
        self.adopt(study_id, run_id)
