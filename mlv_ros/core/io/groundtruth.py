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
Ground truth written next to a simulated study: ``groundtruth.json`` + ``groundtruth.npz``.

Format (version 1)
------------------
``groundtruth.json`` (UTF-8):
    ``format`` = "mlv_ros.groundtruth", ``version`` = 1, ``preset`` (the full preset dict
    used: with the motion's ``num_phases`` it rebuilds the exact motion, see
    :func:`motion_from_groundtruth`; a drawn protocol's preset also holds every imaging option
    and the protocol itself), ``num_phases``, ``cycle_duration_s``, ``times_s`` (list),
    ``es_phase`` (fractional), ``snr`` (null = noiseless), ``seed``, ``frame`` (``apex``,
    ``base_centre``, ``long_axis`` apex → base, ``septum`` (θ = 0), ``e2``, ``length_mm``; LPS mm),
    ``slices`` (one entry per slice in the npz order: ``view`` "SA"/"LA", ``slice_index``,
    ``series_uid``, ``description``, ``rows``, ``columns``, ``geometry`` = ImagePositionPatient /
    ImageOrientationPatient / PixelSpacing / SliceThickness), ``conventions`` (text), ``arrays``
    (what each npz array is), ``regional`` (:func:`mlv_ros.core.sim.regional.regional_truth`: the
    abnormal ``regions``, and per AHA segment at the ES phase ``round(es_phase)`` the true
    Green–Lagrange ``err``, ``ecc``, ``ell`` in the cylindrical frame of the true axis and septum,
    the prescribed ``contraction`` and the truth ``class`` normal / hypokinetic / akinetic /
    dyskinetic with its ``class_thresholds``; absent in files written before it), ``rv``
    (:meth:`LVMotion.rv_insertions`: the true RV insertion points, θ in the phantom's frame and
    LPS directions, and the septum's bisector; null without an RV, absent in files written before
    it), and whatever the writer's ``extra`` adds (``mlv-ros simulate --random``: ``protocol``
    and ``dicom``, the writer's options).
``groundtruth.npz``:
    ``ed_masks`` bool (S, rows, cols) — ED myocardium per slice (slab fraction ≥ 0.5);
    ``material_points`` float64 (N, 3) — ED positions of uniformly sampled myocardium, mm;
    ``trajectories`` float32 (P, N, 3) — their positions at every phase, mm;
    ``levels`` (K,) — fractions of the length from the apex; ``twist_deg``, ``endo_radius_mm``,
    ``mid_radius_mm``, ``epi_radius_mm``, ``thickness_mm``, ``height_mm`` (P, K) — per-level
    curves from :meth:`LVMotion.level_curves`; ``base_descent_mm`` (P,);
    ``strain`` float32 (P, N, 3) — true Green–Lagrange E_rr, E_cc, E_ll of the material points
    at every phase (frame as ``regional``); ``segments`` int8 (N,) — their AHA segment 1–17;
    ``contraction`` float32 (N,) — their prescribed share of normal motion (1 normal, 0 akinetic,
    < 0 dyskinetic). The last three are absent in files written before them.
"""

from __future__ import annotations

from dataclasses import dataclass
import json
from pathlib import Path

from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.types import VIEW_LA, VIEW_NAMES, VIEW_SA
import numpy as np

FORMAT = 'mlv_ros.groundtruth'
VERSION = 1
JSON_NAME = 'groundtruth.json'
NPZ_NAME = 'groundtruth.npz'
_CURVES = (
    'twist_deg',
    'endo_radius_mm',
    'mid_radius_mm',
    'epi_radius_mm',
    'thickness_mm',
    'height_mm',
)
_CONVENTIONS = (
    'Positions in DICOM patient coordinates (LPS), mm. Twist is the rotation about the long axis, '
    'degrees, counter-clockwise seen from the apex looking toward the base positive. Levels are '
    'fractions of the ED apex-to-base length measured from the epicardial apex (material levels). '
    'Phase p is at trigger time p * cycle_duration_s / num_phases; phase 0 = end-diastole.'
)
# What each array of groundtruth.npz holds, written into groundtruth.json for a reader.
_ARRAYS = {
    'ed_masks': "bool (S, rows, cols): ED myocardium per slice, in 'slices' order",
    'material_points': 'float64 (N, 3): ED positions, mm',
    'trajectories': 'float32 (P, N, 3): positions at each phase, mm',
    'levels': '(K,): fractions of the length from the apex',
    **{k: '(P, K)' for k in _CURVES},
    'base_descent_mm': '(P,): base-plane displacement toward the apex, mm',
    'strain': 'float32 (P, N, 3): true Green-Lagrange E_rr, E_cc, E_ll of the material '
    'points',
    'segments': 'int8 (N,): AHA segment 1..17 of the material points (truth frame)',
    'contraction': 'float32 (N,): prescribed share of normal motion (1 normal, 0 '
    'akinetic, <0 dyskinetic)',
}


@dataclass
class GroundTruth:
    """Loaded ground truth (see the module docstring for every field's meaning)."""

    meta: dict
    ed_masks: dict
    geometries: dict
    material_points: np.ndarray
    trajectories: np.ndarray
    curves: dict
    strain: np.ndarray | None = None
    segments: np.ndarray | None = None
    contraction: np.ndarray | None = None

    @property
    def num_phases(self) -> int:
        return int(self.meta['num_phases'])

    @property
    def regional(self) -> dict | None:
        """Return the ``regional`` entry (per-segment ES strain and class), None in older files."""
        return self.meta.get('regional')


def write_groundtruth(
    study, out_dir, n_points: int = 2000, levels=None, extra: dict | None = None
) -> tuple[Path, Path]:
    """
    Write ``groundtruth.json`` and ``groundtruth.npz`` for a simulated study.

    Parameters
    ----------
    study : mlv_ros.core.sim.Study
        The simulated study whose motion and settings are written.
    out_dir : str or Path
        Created if needed.
    n_points : int
        Number of material points whose trajectories are stored.
    levels : array_like, optional
        Levels of the per-level curves (default 0, 0.05, …, 1).
    extra : dict, optional
        JSON-serialisable entries added to ``groundtruth.json`` (they may not replace one of
        its own keys).

    Returns
    -------
    (Path, Path)
        The JSON and NPZ paths.

    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    from mlv_ros.core.sim.regional import (
        regional_truth,
        strain_components,
        truth_frame,
        truth_segments,
    )

    m = study.motion
    lv = np.linspace(0.0, 1.0, 21) if levels is None else np.asarray(levels, dtype=np.float64)
    X = m.sample_myocardium(n_points, seed=study.seed)
    traj = np.stack([m.position(X, p) for p in range(m.num_phases)]).astype(np.float32)
    curves = m.level_curves(lv)
    tf = truth_frame(m)
    strain = np.stack([strain_components(m, X, p, tf) for p in range(m.num_phases)]).astype(
        np.float32
    )
    slices, masks = _slice_entries(study)
    meta = {
        'format': FORMAT,
        'version': VERSION,
        'preset': study.preset,
        'num_phases': m.num_phases,
        'cycle_duration_s': m.cycle_duration,
        'times_s': [float(t) for t in m.times],
        'es_phase': float(m.es_phase),
        'snr': None if study.snr is None or not np.isfinite(study.snr) else float(study.snr),
        'seed': int(study.seed),
        'frame': _frame_entry(m.frame),
        'slices': slices,
        'conventions': _CONVENTIONS,
        'regional': regional_truth(m, seed=study.seed),
        'rv': m.rv_insertions(),
        'arrays': dict(_ARRAYS),
    }
    for k, v in (extra or {}).items():
        if k in meta:
            raise ValueError(f"extra key {k!r} would replace the ground truth's own entry")
        meta[k] = v
    jpath, npath = out / JSON_NAME, out / NPZ_NAME
    with open(jpath, 'w', encoding='utf-8') as fh:
        json.dump(meta, fh, indent=1)
    np.savez_compressed(
        npath,
        ed_masks=np.stack(masks),
        material_points=X,
        trajectories=traj,
        levels=lv,
        base_descent_mm=m.length - m.level_curves([1.0])['height_mm'][:, 0],
        strain=strain,
        segments=truth_segments(m, X, tf).astype(np.int8),
        contraction=m.contraction(X).astype(np.float32),
        **{k: curves[k] for k in _CURVES},
    )
    return jpath, npath


def _frame_entry(f) -> dict:
    """Describe the LV frame of the motion (points and axes in mm, LPS) for groundtruth.json."""
    return {
        'apex': f.apex.tolist(),
        'base_centre': f.base_centre.tolist(),
        'long_axis': f.long_axis.tolist(),
        'septum': f.septum.tolist(),
        'e2': f.e2.tolist(),
        'length_mm': f.length,
    }


def _slice_entries(study) -> tuple[list[dict], list[np.ndarray]]:
    """Describe each slice of the study for groundtruth.json, with its ED myocardium mask."""
    slices = []
    masks = []
    for sl in study.slices:
        key = (sl.view, sl.index)
        mask = study.ed_masks[key]
        masks.append(mask)
        slices.append(
            {
                'view': VIEW_NAMES[sl.view],
                'slice_index': sl.index,
                'series_uid': study.series_uids[key],
                'description': sl.description,
                'rows': int(mask.shape[0]),
                'columns': int(mask.shape[1]),
                'geometry': sl.geometry.to_dicom(),
            }
        )
    return slices, masks


def load_groundtruth(path) -> GroundTruth:
    """
    Read a ground-truth directory (or the path of its JSON file).

    Raises
    ------
    FileNotFoundError
        A file is missing.
    ValueError
        The JSON is not this format or an unsupported version.

    """
    p = Path(path)
    d = p.parent if p.suffix == '.json' else p
    with open(d / JSON_NAME, encoding='utf-8') as fh:
        meta = json.load(fh)
    if meta.get('format') != FORMAT:
        raise ValueError(f'{d / JSON_NAME}: not a {FORMAT} file (format={meta.get("format")!r})')
    if meta.get('version') != VERSION:
        raise ValueError(
            f'{d / JSON_NAME}: unsupported version {meta.get("version")} (need {VERSION})'
        )
    with np.load(d / NPZ_NAME) as z:
        arrays = {k: z[k] for k in z.files}
    views = {'SA': VIEW_SA, 'LA': VIEW_LA}
    masks, geoms = {}, {}
    for i, s in enumerate(meta['slices']):
        key = (views[s['view']], int(s['slice_index']))
        masks[key] = arrays['ed_masks'][i]
        g = s['geometry']
        iop = np.asarray(g['ImageOrientationPatient'], dtype=np.float64)
        geoms[key] = SliceGeometry(
            np.asarray(g['ImagePositionPatient']),
            iop[:3],
            iop[3:],
            g['PixelSpacing'][0],
            g['PixelSpacing'][1],
            g['SliceThickness'],
        )
    curves = {k: arrays[k] for k in (*_CURVES, 'levels', 'base_descent_mm')}
    return GroundTruth(
        meta=meta,
        ed_masks=masks,
        geometries=geoms,
        material_points=arrays['material_points'],
        trajectories=arrays['trajectories'],
        curves=curves,
        strain=arrays.get('strain'),
        segments=arrays.get('segments'),
        contraction=arrays.get('contraction'),
    )


def motion_from_groundtruth(path):
    """
    Rebuild the exact ground-truth motion of a study from its ``groundtruth.json``.

    Parameters
    ----------
    path : str or Path
        Ground-truth directory or the path of its JSON file.

    Returns
    -------
    mlv_ros.core.sim.LVMotion
        The motion the study was simulated with (same preset, phase count and orientation):
        ``motion.position(X, phase)`` equals the stored trajectories.

    Raises
    ------
    FileNotFoundError, ValueError
        As :func:`load_groundtruth` (the JSON is read the same way; the npz is not needed).

    """
    from mlv_ros.core.sim.motion import LVMotion  # io does not otherwise depend on sim

    p = Path(path)
    j = p if p.suffix == '.json' else p / JSON_NAME
    with open(j, encoding='utf-8') as fh:
        meta = json.load(fh)
    if meta.get('format') != FORMAT:
        raise ValueError(f'{j}: not a {FORMAT} file (format={meta.get("format")!r})')
    if meta.get('version') != VERSION:
        raise ValueError(f'{j}: unsupported version {meta.get("version")} (need {VERSION})')
    return LVMotion(meta['preset'], num_phases=int(meta['num_phases']))
