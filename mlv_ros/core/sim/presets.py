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
Phantom presets: YAML files under ``config/phantoms/`` (one per preset, documented inline).

A preset is a nested dict with the sections ``geometry``, ``orientation``, ``motion``,
``imaging`` and ``expected``; :func:`load_preset` reads one and checks it.
"""

from __future__ import annotations

import copy
from pathlib import Path

from mlv_ros.resources import config_dir, config_file
import yaml

PRESET_NAMES = ('normal', 'hypertrophic', 'dilated', 'infarct', 'cylinder')

_REQUIRED = {
    'geometry': ('kind', 'length_mm'),
    'orientation': ('base_centre_mm', 'long_axis', 'septum_hint'),
    'motion': (
        'num_phases',
        'cycle_duration_s',
        'es_fraction',
        'relaxation_fraction',
        'base_descent_mm',
        'endo_radius_ratio_es',
        'twist_apex_deg',
        'twist_base_deg',
        'twist_zero_level',
    ),
    'imaging': (
        'size',
        'pixel_spacing_mm',
        'slice_thickness_mm',
        'subplanes',
        'sa_slices',
        'sa_base_gap_mm',
        'sa_apex_gap_mm',
        'la_planes',
        'la_angle_step_deg',
        'tag_spacing_mm',
        't1_s',
        'myocardium_m0',
        'blood_m0',
        'background_m0',
        'body_radius_mm',
        'psf_sigma_px',
        'snr',
    ),
}
_KIND_KEYS = {
    'prolate': (
        'endo_radius_mm',
        'endo_depth_mm',
        'epi_radius_mm',
        'septal_extra_mm',
        'atrium_height_mm',
    ),
    'cylinder': ('inner_radius_mm', 'outer_radius_mm'),
}


def available_presets() -> list[str]:
    """Names of the preset files in ``config/phantoms/``."""
    return sorted(p.stem for p in (config_dir() / 'phantoms').glob('*.yaml'))


def load_preset(name_or_path: str | Path | dict) -> dict:
    """
    Load and validate a phantom preset.

    Parameters
    ----------
    name_or_path : str, Path or dict
        A preset name (``normal``, ``hypertrophic``, ``dilated``, ``infarct``, ``cylinder``), a
        path to a YAML file with the same layout, or an already loaded dict (deep-copied and
        validated).

    Returns
    -------
    dict
        The preset (a fresh copy the caller may modify).

    Raises
    ------
    FileNotFoundError
        No such preset file.
    ValueError
        A required section or key is missing or a value is out of range.

    """
    if isinstance(name_or_path, dict):
        preset = copy.deepcopy(name_or_path)
        source = '<dict>'
    else:
        path = Path(name_or_path)
        if path.suffix not in ('.yaml', '.yml'):
            try:
                path = config_file('phantoms', f'{name_or_path}.yaml')
            except FileNotFoundError:
                raise FileNotFoundError(
                    f'unknown phantom preset {str(name_or_path)!r}; available: '
                    f'{", ".join(available_presets())}'
                ) from None
        with open(path, encoding='utf-8') as fh:
            preset = yaml.safe_load(fh)
        source = str(path)
    validate_preset(preset, source)
    return preset


def validate_preset(preset: dict, source: str = '<preset>') -> None:
    """Raise ``ValueError`` naming the first missing key or inconsistent value."""
    if not isinstance(preset, dict):
        raise ValueError(f'{source}: a preset must be a mapping, got {type(preset).__name__}')
    for section, keys in _REQUIRED.items():
        sec = preset.get(section)
        if not isinstance(sec, dict):
            raise ValueError(f"{source}: missing section '{section}'")
        for k in keys:
            if k not in sec:
                raise ValueError(f"{source}: missing key '{section}.{k}'")
    kind = preset['geometry']['kind']
    if kind not in _KIND_KEYS:
        raise ValueError(
            f'{source}: geometry.kind must be one of {sorted(_KIND_KEYS)}, got {kind!r}'
        )
    for k in _KIND_KEYS[kind]:
        if k not in preset['geometry']:
            raise ValueError(f"{source}: missing key 'geometry.{k}' (needed for kind {kind!r})")
    g, m, im = preset['geometry'], preset['motion'], preset['imaging']
    if kind == 'prolate':
        if not 0 < g['endo_radius_mm'] < g['epi_radius_mm']:
            raise ValueError(f'{source}: need 0 < endo_radius_mm < epi_radius_mm')
        if not 0 < g['endo_depth_mm'] < g['length_mm']:
            raise ValueError(f'{source}: need 0 < endo_depth_mm < length_mm')
    else:
        if not 0 < g['inner_radius_mm'] < g['outer_radius_mm']:
            raise ValueError(f'{source}: need 0 < inner_radius_mm < outer_radius_mm')
    if int(m['num_phases']) < 2:
        raise ValueError(f'{source}: motion.num_phases must be >= 2, got {m["num_phases"]}')
    if not (
        0 < m['es_fraction']
        and 0 < m['relaxation_fraction']
        and m['es_fraction'] + m['relaxation_fraction'] <= 1.0
    ):
        raise ValueError(
            f'{source}: need es_fraction > 0, relaxation_fraction > 0 and their sum <= 1'
        )
    if not 0 <= m['base_descent_mm'] < g['length_mm']:
        raise ValueError(f'{source}: motion.base_descent_mm must be in [0, length_mm)')
    if not 0 < m['endo_radius_ratio_es'] <= 1.5:
        raise ValueError(f'{source}: motion.endo_radius_ratio_es must be in (0, 1.5]')
    tau = m.get('apex_thickening')
    if tau is not None and (
        isinstance(tau, bool) or not isinstance(tau, (int, float)) or not 0.0 <= tau <= 0.8
    ):
        raise ValueError(
            f'{source}: motion.apex_thickening must be a number in [0, 0.8] (the ES axial '
            f'thickening of the apical wall, fraction) or absent, got {tau!r}'
        )
    if not 0 < m['twist_zero_level'] < 1:
        raise ValueError(f'{source}: motion.twist_zero_level must be in (0, 1)')
    if m.get('regions') is not None:
        from mlv_ros.core.sim.regional import check_regions  # (overlap with an infarct: LVMotion)

        check_regions(m['regions'], g, where=f'{source}: motion.regions')
    if g.get('rv') is not None:
        from mlv_ros.core.sim.rv import check_rv

        check_rv(g['rv'], where=f'{source}: geometry.rv')
    if int(im['sa_slices']) < 2 or int(im['subplanes']) < 1 or int(im['size']) < 16:
        raise ValueError(f'{source}: imaging needs sa_slices >= 2, subplanes >= 1, size >= 16')
    if im.get('tag_lines', 'grid') not in ('grid', 'single'):
        raise ValueError(
            f"{source}: imaging.tag_lines must be 'grid' or 'single', got {im['tag_lines']!r}"
        )
