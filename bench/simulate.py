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
Benchmark: simulate the default study (normal preset, 25 phases x 11 slices, 256^2).

Prints one JSON document: wall time of the simulation (and, separately, of writing it as DICOM),
peak resident memory of the process, and whether the issue's limits (30 s, 2 GB) are met.
Usage: ``mlv-ros bench simulate [--preset NAME] [--no-write]``.
"""

import argparse
import json
import resource
import sys
import tempfile
import time


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--preset', default='normal')
    ap.add_argument('--no-write', action='store_true', help='skip the DICOM write timing')
    args = ap.parse_args(argv)

    from mlv_ros.core.io import write_study_dicom
    from mlv_ros.core.sim import simulate_study

    t0 = time.perf_counter()
    study = simulate_study(args.preset)
    t_sim = time.perf_counter() - t0
    t_write = None
    if not args.no_write:
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            write_study_dicom(study, d)
            t_write = time.perf_counter() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB
    n = len(study.frames)
    out = {
        'benchmark': 'simulate',
        'preset': args.preset,
        'images': n,
        'phases': study.num_phases,
        'slices': len(study.slices),
        'size': int(study.frames[0].image.shape[0]),
        'simulate_s': round(t_sim, 3),
        'ms_per_image': round(1000.0 * t_sim / n, 2),
        'write_dicom_s': None if t_write is None else round(t_write, 3),
        'peak_rss_mb': round(peak_mb, 1),
        'limit_s': 30.0,
        'limit_mb': 2048.0,
        'ok': bool(t_sim <= 30.0 and peak_mb <= 2048.0),
    }
    print(json.dumps(out))
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
