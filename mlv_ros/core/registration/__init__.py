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
ED myocardium segmentation, curvature landmarks and meshless-model registration.

Paper §2.1 model initialisation, §3.2 registration, Fig. 7. Pure numpy/scipy/OpenCV.

Typical use (the ROS ``registration`` node)::

    from mlv_ros.core.registration import register_ed
    res = register_ed(ed_frames, num_particles=5000)       # list[Frame], SA + LA, phase 0
    model = MeshlessModel(res.particles, res.frame)         # ready for tracking
    for r in res.slice_reports: print(r.view, r.slice_index, r.ok, r.reason)

Modules: :mod:`.segment` (tag-energy segmentation), :mod:`.landmarks` (contours, curvature,
landmarks), :mod:`.initialise` (3-D reconstruction, particles, polar frame), :mod:`.register`
(:func:`register_ed`). User masks are per-slice boolean arrays (NIfTI reader: not yet).
"""

import importlib

# Name → the submodule that defines it, imported on first use (PEP 562): the tag detector needs
# only .segment and .streaming, and importing .register with it (pydicom, scipy.interpolate and
# scipy.optimize) cost each of its processes ~0.4 s of CPU at start.
_LAZY = {
    'masks_for_frames': 'nifti',
    'MIN_SA_SLICES': 'register',
    'register_ed': 'register',
    'RegistrationResult': 'register',
    'segment_around_axis': 'register',
    'SliceReport': 'register',
    'StreamingMasker': 'streaming',
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    """Return ``name`` of :data:`_LAZY` from its submodule, importing it the first time."""
    if name not in _LAZY:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    value = getattr(importlib.import_module(f'{__name__}.{_LAZY[name]}'), name)
    globals()[name] = value
    return value


def __dir__():
    """List the module's names with the lazily imported ones."""
    return sorted({*globals(), *_LAZY})
