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
Benchmark of ED registration on full-size simulated studies (prints JSON).

Usage: .venv/bin/python bench/registration.py [--presets normal hypertrophic] [--snr 20]
       [--particles 5000] [--quick]
"""

import argparse
import json
import time

from mlv_ros.core.registration import register_ed
from mlv_ros.core.registration.segment import dice
from mlv_ros.core.sim import simulate_study
import numpy as np
from scipy.spatial import cKDTree


def gt_surface(motion, which):
    th = np.linspace(-np.pi, np.pi, 180, endpoint=False)
    z0 = 0.0 if which == 'epi' else motion.length - motion.endo_c
    z = z0 + (motion.length - z0) * (1 - np.cos(0.5 * np.pi * np.linspace(0, 1, 400)))
    Z, T = np.meshgrid(z, th, indexing='ij')
    r = motion.epi_radius(Z, T) if which == 'epi' else motion.endo_radius(Z)
    return motion.frame.from_local(r.ravel(), T.ravel(), Z.ravel())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--presets', nargs='+', default=['normal', 'hypertrophic'])
    ap.add_argument('--snr', type=float, default=20.0)
    ap.add_argument('--particles', type=int, default=5000)
    ap.add_argument('--quick', action='store_true')
    a = ap.parse_args()
    out = []
    for preset in a.presets:
        st = simulate_study(preset, snr=a.snr, quick=a.quick, num_phases=2)
        ed = [f for f in st.frames if f.phase_index == 0]
        t0 = time.perf_counter()
        res = register_ed(ed, num_particles=a.particles)
        wall = time.perf_counter() - t0
        m = st.motion
        out.append(
            {
                'preset': preset,
                'snr': a.snr,
                'size': int(ed[0].image.shape[0]),
                'particles': a.particles,
                'wall_s': round(wall, 3),
                'timings_s': {k: round(v, 3) for k, v in res.timings.items()},
                'dice': {
                    f'{"SA" if k[0] == 0 else "LA"}{k[1]}': round(
                        dice(res.masks.get(k, np.zeros(1, bool)), st.ed_masks[k]), 4
                    )
                    for k in st.keys
                },
                'inside_fraction': round(float(m.inside_myocardium(res.particles).mean()), 4),
                'surface_distance_mm': {
                    w: round(float(cKDTree(gt_surface(m, w)).query(res.surfaces[w])[0].mean()), 3)
                    for w in ('endo', 'epi')
                },
                'landmark_residual_mm': round(res.state.residual, 3),
                'warnings': res.warnings,
            }
        )
    print(json.dumps(out, indent=1))


if __name__ == '__main__':
    main()
