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

"""A whole simulated tagged-MRI study: every planned slice at every phase, plus ground truth."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
import hashlib
import json

from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.sim.imaging import draw_noise, ImageSynthesizer, plan_slices, PlannedSlice
from mlv_ros.core.sim.motion import LVMotion
from mlv_ros.core.sim.presets import load_preset
from mlv_ros.core.sim.protocol import protocol_identity
from mlv_ros.core.types import Frame, VIEW_NAMES, VIEW_SA
import numpy as np

Key = tuple[int, int]  # (view, slice_index)

# Cheap settings for tests and demos (a few seconds): 128², 10 phases, 3 sub-planes.
QUICK = {'size': 128, 'num_phases': 10, 'subplanes': 3}


def _uid(*parts) -> str:
    """Deterministic DICOM UID under the ISO '2.25' UUID arc (a 128-bit hash of ``parts``)."""
    h = hashlib.sha256('|'.join(str(p) for p in parts).encode()).digest()[:16]
    return '2.25.' + str(int.from_bytes(h, 'big'))


@dataclass
class Study:
    """
    A simulated study.

    Attributes
    ----------
    frames : list of Frame
        All slices × phases, slice-major (SA in index order, then LA), float32 images with
        ``myocardium_m0 = 1`` (untagged myocardium) as the intensity unit.
    motion : LVMotion
        The ground truth.
    preset : dict
        The preset used (with overrides applied; a drawn protocol's preset carries it under
        ``"protocol"``, see :mod:`mlv_ros.core.sim.protocol`).
    slices : list of PlannedSlice
        Planned planes in frame order.
    geometries : dict
        ``(view, slice_index) -> SliceGeometry``.
    ed_masks : dict
        ``(view, slice_index) -> ndarray of bool (rows, cols)``: ED myocardium, slab-weighted
        myocardial fraction ≥ 0.5.
    series_uids : dict
        ``(view, slice_index) -> str`` (one SeriesInstanceUID per slice location).
    study_uid, frame_of_reference_uid : str
    snr : float or None
    seed : int

    """

    frames: list[Frame]
    motion: LVMotion
    preset: dict
    slices: list[PlannedSlice]
    geometries: dict[Key, SliceGeometry]
    ed_masks: dict[Key, np.ndarray]
    series_uids: dict[Key, str]
    study_uid: str
    frame_of_reference_uid: str
    snr: float | None
    seed: int
    descriptions: dict[Key, str] = field(default_factory=dict)

    @property
    def num_phases(self) -> int:
        return self.motion.num_phases

    @property
    def keys(self) -> list[Key]:
        """``(view, slice_index)`` of every slice, in frame order."""
        return [(s.view, s.index) for s in self.slices]

    def cine(self, view: int, slice_index: int) -> list[Frame]:
        """Frames of one slice ordered by phase."""
        fr = [f for f in self.frames if f.view == view and f.slice_index == slice_index]
        if not fr:
            raise ValueError(f'no slice (view={view}, slice_index={slice_index}) in this study')
        return sorted(fr, key=lambda f: f.phase_index)


class SliceMajorNoise:
    """
    The study's one noise generator, drawn slice-major, handed to frames in any order.

    :func:`simulate_study` draws every image's noise from one ``default_rng(seed)``, slice by
    slice and within a slice phase by phase. This keeps a copy of the generator where each slice's
    draws begin (where the slice before it ends: drawn to its end already in slice-major order,
    else drawn, and dropped, once), so a frame rendered alone, or phase-major, gets the very
    noise it gets in the whole study. Within a slice, phases asked for in order cost nothing
    extra; a phase behind the slice's position starts again from the slice's first draw.

    Parameters
    ----------
    seed : int
        The study's seed.
    num_phases : int
        Phases per slice.
    shape : tuple of int
        Image (rows, cols).

    """

    def __init__(self, seed: int, num_phases: int, shape: tuple[int, int]):
        self._num_phases, self._shape = int(num_phases), tuple(shape)
        # per slice position: the generator's state at its first draw
        self._starts: list[dict] = [np.random.default_rng(seed).bit_generator.state]
        self._at: dict[int, tuple[np.random.Generator, int]] = {}  # slice → (generator, phase)

    def _skip(self, rng: np.random.Generator, phases: int) -> None:
        for _ in range(phases):
            draw_noise(rng, self._shape)

    def generator(self, position: int, phase: int) -> np.random.Generator:
        """
        Return the generator positioned at one frame's first draw (render that frame with it).

        Parameters
        ----------
        position : int
            The slice's position in frame order (0-based).
        phase : int
            The phase, ``0 .. num_phases - 1``.

        Returns
        -------
        numpy.random.Generator
            Ready for that frame's :func:`draw_noise`; the next call for the same slice and the
            following phase continues from where that draw ends.

        """
        while len(self._starts) <= position:  # the next slice starts where the last one ends
            last = len(self._starts) - 1
            rng, at = self._at.get(last, (None, 0))
            if at < self._num_phases:  # not drawn to its end (phase-major): draw it again
                rng = self._from_start(last)
                self._skip(rng, self._num_phases)
            self._starts.append(rng.bit_generator.state)
        rng, at = self._at.get(position, (None, 0))
        if rng is None or phase < at:
            rng, at = self._from_start(position), 0
        self._skip(rng, phase - at)
        self._at[position] = (rng, phase + 1)
        return rng

    def _from_start(self, position: int) -> np.random.Generator:
        rng = np.random.default_rng()
        rng.bit_generator.state = self._starts[position]
        return rng


class StudyRenderer:
    """
    A simulated study's plan, rendering any frame on demand (lazily, in any order).

    Noise comes from the study's one generator positioned at the frame's draws
    (:class:`SliceMajorNoise`), so a frame rendered alone, or the study rendered phase-major,
    equals the same frame of :func:`simulate_study`'s whole study, bit for bit; each slice's
    :class:`ImageSynthesizer` is built the first time one of its frames is rendered and kept.

    Parameters
    ----------
    preset, snr, seed
        As :func:`simulate_study`'s.
    heart_shift_mm : array_like, shape (3,), optional
        Where the heart (and everything round it) sits relative to the planned planes, patient
        mm: a breath-hold that differs from the one the planes were planned in. The images show
        the shifted heart; the frames keep the planned geometry (the scanner does not know).
        The truth stays the unshifted heart's. Default: none.
    **overrides
        ``size``, ``num_phases``, ``subplanes``, ``pixel_spacing``, ``quick``: as
        :func:`simulate_study`'s.

    Attributes
    ----------
    preset : dict
        The preset with the overrides applied.
    motion : LVMotion
        The ground truth.
    slices : list of PlannedSlice
        Planned planes in frame order (SA in index order, then LA).
    study_uid, frame_of_reference_uid : str
    series_uids : dict
        ``(view, slice_index) -> str``.
    snr : float or None
    seed : int

    """

    def __init__(
        self,
        preset='normal',
        snr: float | None = 20.0,
        seed: int = 0,
        heart_shift_mm=None,
        **overrides,
    ):
        self.preset = p = _preset_with(preset, **overrides)
        self.size = p['imaging']['size']
        self.motion = LVMotion(p)
        self.slices = plan_slices(self.motion, p['imaging'], self.size)
        self.snr, self.seed = snr, int(seed)
        # A drawn protocol (sim.protocol) joins the UID's parts, so two protocols never share one.
        extra = (
            (json.dumps(protocol_identity(p['protocol']), sort_keys=True),)
            if p.get('protocol')
            else ()
        )
        self.study_uid = _uid('study', p['name'], seed, self.size, self.motion.num_phases, *extra)
        self.frame_of_reference_uid = _uid('for', p['name'], seed)
        self.series_uids = {
            (sl.view, sl.index): _uid('series', self.study_uid, sl.view, sl.index)
            for sl in self.slices
        }
        self._planes = {(sl.view, sl.index): sl for sl in self.slices}
        # Rendered through planes moved by −shift: the heart sits at +shift relative to them.
        shift = np.zeros(3) if heart_shift_mm is None else np.asarray(heart_shift_mm, float)
        if shift.shape != (3,) or not np.isfinite(shift).all():
            raise ValueError(
                f'heart_shift_mm must be 3 finite numbers (mm), got {heart_shift_mm!r}'
            )
        self._render_planes = {
            key: sl if not shift.any() else replace(sl, geometry=_moved(sl.geometry, -shift))
            for key, sl in self._planes.items()
        }
        self._position = {(sl.view, sl.index): i for i, sl in enumerate(self.slices)}
        self._noise = SliceMajorNoise(seed, self.motion.num_phases, (self.size, self.size))
        self._synths: dict[Key, ImageSynthesizer] = {}

    @property
    def keys(self) -> list[Key]:
        """``(view, slice_index)`` of every slice, in frame order."""
        return [(s.view, s.index) for s in self.slices]

    def synthesizer(self, view: int, slice_index: int) -> ImageSynthesizer:
        """Return one slice's ImageSynthesizer, built the first time it is asked for."""
        key = (int(view), int(slice_index))
        if key not in self._planes:
            raise ValueError(f'no slice (view={view}, slice_index={slice_index}) in this study')
        if key not in self._synths:
            self._synths[key] = ImageSynthesizer(
                self.motion, self._render_planes[key], self.size, self.preset['imaging']
            )
        return self._synths[key]

    def frame(self, view: int, slice_index: int, phase: int, image: bool = True) -> Frame:
        """
        Return one frame, rendered now (``image=False``: its metadata only, ``image`` None).

        Raises
        ------
        ValueError
            No such slice, or ``phase`` outside ``0 .. num_phases - 1``.

        """
        key, n = (int(view), int(slice_index)), self.motion.num_phases
        if key not in self._planes:
            raise ValueError(f'no slice (view={view}, slice_index={slice_index}) in this study')
        if not 0 <= int(phase) < n:
            raise ValueError(f'phase must be in 0..{n - 1}, got {phase}')
        t = float(self.motion.times[int(phase)])
        img = None
        if image:
            rng = None
            if self.snr is not None and np.isfinite(self.snr):
                rng = self._noise.generator(self._position[key], int(phase))
            img = self.synthesizer(*key).render(int(phase), t, self.snr, rng)
        return Frame(
            image=img,
            geometry=self._planes[key].geometry,
            view=key[0],
            slice_index=key[1],
            phase_index=int(phase),
            num_phases=n,
            trigger_time=t,
            cycle_duration=self.motion.cycle_duration,
            series_uid=self.series_uids[key],
        )

    def ed_mask(self, view: int, slice_index: int) -> np.ndarray:
        """Return one slice's ED myocardium (slab-weighted fraction >= 0.5), bool (rows, cols)."""
        myo, _ = self.synthesizer(view, slice_index).tissue_fractions(0)
        return myo >= 0.5


def _moved(geometry: SliceGeometry, offset) -> SliceGeometry:
    """Return ``geometry`` translated by ``offset`` (patient mm), its axes and grid unchanged."""
    return replace(geometry, image_position=np.asarray(geometry.image_position, float) + offset)


def simulate_study(
    preset='normal',
    snr: float | None = 20.0,
    size: int | None = None,
    num_phases: int | None = None,
    seed: int = 0,
    subplanes: int | None = None,
    pixel_spacing: float | None = None,
    quick: bool = False,
    progress: Callable[[int, int], None] | None = None,
    heart_shift_mm=None,
) -> Study:
    """
    Simulate a tagged cine study (SA stack + LA planes) of a phantom preset.

    Parameters
    ----------
    preset : str, Path or dict
        Preset name (``normal``, ``hypertrophic``, ``dilated``, ``infarct``, ``cylinder``), YAML
        path or dict.
    snr : float or None
        ``myocardium_m0 / σ`` of the Rician noise; ``None`` or ``inf`` → noiseless.
    size : int, optional
        Rows = columns (default from the preset, 256; pixel spacing stays as in the preset, so a
        smaller size means a smaller field of view).
    num_phases : int, optional
        Phases per cycle (default from the preset, 25).
    seed : int
        Seeds the noise (one ``default_rng(seed)`` drawn slice-major, in frame order) and the
        UIDs.
    subplanes : int, optional
        Through-slice sub-planes (default from the preset, 5).
    pixel_spacing : float, optional
        mm; default from the preset (1.3 mm).
    quick : bool
        Use :data:`QUICK` (128², 10 phases, 3 sub-planes) for anything not given explicitly.
    progress : callable, optional
        ``progress(done, total)`` after each image.
    heart_shift_mm : array_like, shape (3,), optional
        The heart's shift from the planned planes, patient mm (:class:`StudyRenderer`).

    Returns
    -------
    Study

    """
    r = StudyRenderer(
        preset,
        snr,
        seed,
        heart_shift_mm,
        size=size,
        num_phases=num_phases,
        subplanes=subplanes,
        pixel_spacing=pixel_spacing,
        quick=quick,
    )
    total = len(r.slices) * r.motion.num_phases
    frames, masks, geoms, desc = [], {}, {}, {}
    for sl in r.slices:
        key = (sl.view, sl.index)
        geoms[key], desc[key] = sl.geometry, sl.description
        masks[key] = r.ed_mask(*key)
        for ph in range(r.motion.num_phases):
            frames.append(r.frame(sl.view, sl.index, ph))
            if progress is not None:
                progress(len(frames), total)
    return Study(
        frames=frames,
        motion=r.motion,
        preset=r.preset,
        slices=r.slices,
        geometries=geoms,
        ed_masks=masks,
        series_uids=dict(r.series_uids),
        study_uid=r.study_uid,
        frame_of_reference_uid=r.frame_of_reference_uid,
        snr=snr,
        seed=seed,
        descriptions=desc,
    )


def _preset_with(
    preset, size=None, num_phases=None, subplanes=None, pixel_spacing=None, quick=False
) -> dict:
    """
    Load a preset with simulate_study's overrides applied (its parameters of the same names).

    Returns
    -------
    dict
        The preset; ``imaging.size`` is the image size in pixels (int).

    Raises
    ------
    ValueError
        ``size`` below 16 pixels.

    """
    p = load_preset(preset)
    if quick:
        size = size or QUICK['size']
        num_phases = num_phases or QUICK['num_phases']
        subplanes = subplanes or QUICK['subplanes']
    im = p['imaging']
    n = int(size or im['size'])
    if n < 16:
        raise ValueError(f'size must be >= 16 pixels, got {n}')
    if num_phases is not None:
        p['motion']['num_phases'] = int(num_phases)
    if subplanes is not None:
        im['subplanes'] = int(subplanes)
    if pixel_spacing is not None:
        im['pixel_spacing_mm'] = float(pixel_spacing)
    im['size'] = n
    return p


def line_pair_study(
    preset,
    first: Study,
    turn_deg: float = 90.0,
    seed: int | None = None,
    shift_mm=(0.0, 0.0),
    through_mm: float = 0.0,
    **kwargs,
) -> Study:
    """
    Simulate the second single-line series of every slice of ``first``: its lines turned.

    Vendors acquire single-line tags of one slice twice, in separate breath-holds, the lines
    turned between them (``tag_lines: pair`` of :mod:`mlv_ros.core.sim.protocol`). The second
    study is the same heart and planes with ``imaging.tag_angle_deg`` + ``turn_deg`` and its own
    noise; it joins ``first``'s study and frame of reference with series of its own (UIDs and
    descriptions ``… lines 2``). Its breath-hold may put the heart elsewhere: ``shift_mm`` along
    the SA images' rows and columns and ``through_mm`` along the long axis (apex → base), one
    rigid shift for the whole second acquisition (every slice, SA and LA, sees the same 3-D
    shift, in its plane or through it); the DICOM geometry is the planned one either way.

    Parameters
    ----------
    preset : dict
        ``first``'s preset (``imaging.tag_lines: single``).
    first : Study
        The first series of every slice.
    turn_deg : float
        Angle between the two families, degrees.
    seed : int, optional
        Noise seed (default ``first.seed + 1``: noise independent of the first's).
    shift_mm : sequence of 2 float
        The heart's in-plane shift in the second breath-hold, along the SA rows and columns, mm.
    through_mm : float
        Its shift along the long axis (apex → base), mm.
    **kwargs
        :func:`simulate_study`'s other arguments, as given for ``first``.

    Returns
    -------
    Study
        The second series; its truth is ``first``'s.

    Raises
    ------
    ValueError
        ``preset`` is not a single-line preset, or ``first`` has no SA slice to take the shift's
        directions from while one is asked for.

    """
    p = load_preset(preset)
    im = p['imaging']
    if im.get('tag_lines', 'grid') != 'single':
        raise ValueError(
            f"a line pair needs imaging.tag_lines 'single', got {im.get('tag_lines')!r}"
        )
    im['tag_angle_deg'] = (float(im.get('tag_angle_deg', 0.0)) + float(turn_deg)) % 180.0
    shift = np.zeros(3)
    if any(shift_mm) or through_mm:
        sa = [g for (view, _), g in sorted(first.geometries.items()) if view == VIEW_SA]
        if not sa:
            raise ValueError('a breath-hold shift of a line pair needs an SA slice (its axes)')
        shift = (
            float(shift_mm[0]) * np.asarray(sa[0].row_direction)
            + float(shift_mm[1]) * np.asarray(sa[0].column_direction)
            + float(through_mm) * first.motion.frame.long_axis
        )
    second = simulate_study(
        p,
        snr=first.snr,
        seed=first.seed + 1 if seed is None else int(seed),
        heart_shift_mm=shift,
        **kwargs,
    )
    uids = {k: _uid('series', first.study_uid, 'lines 2', *k) for k in second.series_uids}
    return replace(
        second,
        frames=[replace(f, series_uid=uids[(f.view, f.slice_index)]) for f in second.frames],
        series_uids=uids,
        study_uid=first.study_uid,
        frame_of_reference_uid=first.frame_of_reference_uid,
        descriptions={k: f'tagged {VIEW_NAMES[k[0]]} {k[1]} lines 2' for k in uids},
    )
