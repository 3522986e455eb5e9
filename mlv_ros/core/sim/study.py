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

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
import hashlib
import json

from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.sim.imaging import ImageSynthesizer, plan_slices, PlannedSlice
from mlv_ros.core.sim.motion import LVMotion
from mlv_ros.core.sim.presets import load_preset
from mlv_ros.core.types import Frame
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
        Seeds the noise (one ``default_rng(seed)`` drawn in frame order) and the UIDs.
    subplanes : int, optional
        Through-slice sub-planes (default from the preset, 5).
    pixel_spacing : float, optional
        mm; default from the preset (1.3 mm).
    quick : bool
        Use :data:`QUICK` (128², 10 phases, 3 sub-planes) for anything not given explicitly.
    progress : callable, optional
        ``progress(done, total)`` after each image.

    Returns
    -------
    Study

    """
    p = _preset_with(preset, size, num_phases, subplanes, pixel_spacing, quick)
    im = p['imaging']
    n = im['size']
    motion = LVMotion(p)
    slices = plan_slices(motion, im, n)
    rng = np.random.default_rng(seed)
    # A drawn protocol (sim.protocol) joins the UID's parts, so two protocols never share one.
    extra = (json.dumps(p['protocol'], sort_keys=True),) if p.get('protocol') else ()
    study_uid = _uid('study', p['name'], seed, n, motion.num_phases, *extra)
    for_uid = _uid('for', p['name'], seed)
    total = len(slices) * motion.num_phases
    frames, masks, uids, geoms, desc = [], {}, {}, {}, {}
    done = 0
    for sl in slices:
        key = (sl.view, sl.index)
        syn = ImageSynthesizer(motion, sl, n, im)
        uid = _uid('series', study_uid, sl.view, sl.index)
        uids[key], geoms[key], desc[key] = uid, sl.geometry, sl.description
        myo, _ = syn.tissue_fractions(0)
        masks[key] = myo >= 0.5
        for frame in _render_cine(syn, sl, motion, snr, rng, uid):
            frames.append(frame)
            done += 1
            if progress is not None:
                progress(done, total)
    return Study(
        frames=frames,
        motion=motion,
        preset=p,
        slices=slices,
        geometries=geoms,
        ed_masks=masks,
        series_uids=uids,
        study_uid=study_uid,
        frame_of_reference_uid=for_uid,
        snr=snr,
        seed=seed,
        descriptions=desc,
    )


def _render_cine(syn, sl, motion, snr, rng, uid: str) -> Iterator[Frame]:
    """
    Render one slice's cine, phase by phase, as it is consumed (noise drawn in that order).

    Parameters
    ----------
    syn : ImageSynthesizer
        The slice's synthesizer.
    sl : PlannedSlice
        The slice.
    motion : LVMotion
        The motion (phases, trigger times in s, cycle duration in s).
    snr : float or None
        Noise level (None: noiseless).
    rng : numpy.random.Generator
        The study's noise generator.
    uid : str
        The slice's SeriesInstanceUID.

    Yields
    ------
    Frame

    """
    for ph in range(motion.num_phases):
        t = float(motion.times[ph])
        img = syn.render(ph, t, snr, rng)
        yield Frame(
            image=img,
            geometry=sl.geometry,
            view=sl.view,
            slice_index=sl.index,
            phase_index=ph,
            num_phases=motion.num_phases,
            trigger_time=t,
            cycle_duration=motion.cycle_duration,
            series_uid=uid,
        )


def _preset_with(preset, size, num_phases, subplanes, pixel_spacing, quick) -> dict:
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
