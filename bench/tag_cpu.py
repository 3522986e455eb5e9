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
CPU time of the tag detector's work on the default study, replayed as the node does.

The default study (``normal`` preset, 256², 25 phases, SNR 20, seed 0: what ``mlv-ros run
--phantom normal`` and ``bench pipeline`` simulate) goes frame by frame, in the source's
phase-major order, through what ``nodes/tag_detector.py`` runs per frame:
``StreamingMasker.observe_geometry``, at a slice's phase 0 its ED mask
(``StreamingMasker.ed_mask``) and a new :class:`mlv_ros.core.tags.SliceTracker`, then
``SliceTracker.update``. The detector is a process
of its own in the graph, so its CPU time is the study's wall time there.

Each repeat runs in a fresh process (no kept running medians or kernel banks), on one
BLAS/OpenCV thread as every graph process runs (:func:`mlv_ros.threads.compute_threads`), and
measures process time: ``masks_s`` (the 11 ED masks), ``tracker_s`` (275 tracker updates) and
``total_s``. With ``--baseline DIR`` (a source tree holding another ``mlv_ros``, e.g. ``git
archive REV mlv_ros | tar -x -C DIR``) the repeats alternate between that tree and this one, and
each tag point of the two is compared (``max_point_diff_px``, ``same_tracks``).

Usage: ``mlv-ros bench tag_cpu [-- --repeat 3 --baseline DIR]``
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import pickle
import shutil
import statistics
import subprocess
import sys
import tempfile
import time


def replay(study_path: Path, out_path: Path) -> dict:
    """
    Run the detector's per-frame work over a pickled frame list; return its process times.

    Parameters
    ----------
    study_path : Path
        Pickled list of :class:`mlv_ros.core.types.Frame`, in publishing order.
    out_path : Path
        Where the tag points go (pickled dict (view, slice, phase) → (pixel_rc, track_id)).

    Returns
    -------
    dict
        ``masks_s``, ``tracker_s``, ``total_s``: process time, s.

    """
    import cv2  # noqa: F401  (imported before compute_threads holds its pool)
    from mlv_ros.core.registration.streaming import StreamingMasker
    from mlv_ros.core.tags import SliceTracker
    from mlv_ros.threads import compute_threads

    frames = pickle.loads(study_path.read_bytes())
    masker, trackers, points = StreamingMasker(), {}, {}
    masks = tracker = 0.0
    with compute_threads():
        t0 = time.process_time()
        for f in frames:
            masker.observe_geometry(f)
            key, mask = (f.view, f.slice_index), None
            if key not in trackers or f.phase_index == 0:
                trackers[key] = SliceTracker(f.geometry)
                t = time.process_time()
                mask, _ = masker.ed_mask(f)
                masks += time.process_time() - t
            t = time.process_time()
            p = trackers[key].update(f, mask=mask)
            tracker += time.process_time() - t
            points[(*key, f.phase_index)] = (p.pixel_rc, p.track_id)
        total = time.process_time() - t0
    out_path.write_bytes(pickle.dumps(points))
    return {'masks_s': masks, 'tracker_s': tracker, 'total_s': total}


def compare(a: dict, b: dict) -> dict:
    """Return the largest tag-point difference (px) and whether every frame has the same ids."""
    same = a.keys() == b.keys() and all(
        (a[k][1] == b[k][1]).all() and len(a[k][1]) == len(b[k][1]) for k in a
    )
    diff = max(
        (float(abs(a[k][0] - b[k][0]).max()) for k in a if same and len(a[k][1])), default=0.0
    )
    return {'same_tracks': bool(same), 'max_point_diff_px': diff if same else None}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--repeat', type=int, default=3, help='repeats per source tree (median)')
    ap.add_argument('--baseline', default='', help='source tree of another mlv_ros to alternate')
    ap.add_argument('--once', nargs=2, help=argparse.SUPPRESS)  # STUDY OUT: one repeat, here
    args = ap.parse_args()
    if args.once:
        print(json.dumps(replay(Path(args.once[0]), Path(args.once[1]))))
        return
    from mlv_ros.core.sim import load_preset, simulate_study

    tmp = Path(tempfile.mkdtemp(prefix='mlv-bench-tag-cpu-'))
    try:  # the study and the tag points (~70 MB) go with the run
        study = tmp / 'study.pkl'
        frames = simulate_study(load_preset('normal'), snr=20.0, size=256, num_phases=25, seed=0)
        study.write_bytes(pickle.dumps(list(frames.frames)))
        trees = {'current': ''}
        if args.baseline:
            trees = {'baseline': args.baseline, 'current': ''}
        runs = {name: [] for name in trees}
        for i in range(args.repeat):
            for name, tree in trees.items():  # alternated: the machine's load falls on both alike
                env = dict(os.environ)
                if tree:  # ahead of the editable install (a .pth entry): via sys.path in the child
                    code = (
                        f'import sys; sys.path.insert(0, {tree!r}); sys.argv[0] = {__file__!r}; '
                        f'exec(open({__file__!r}).read())'
                    )
                    cmd = [sys.executable, '-c', code]
                else:
                    cmd = [sys.executable, __file__]
                out = tmp / f'{name}{i}.pkl'
                res = subprocess.run(
                    cmd + ['--once', str(study), str(out)],
                    env=env,
                    check=True,
                    capture_output=True,
                    text=True,
                )
                runs[name].append(json.loads(res.stdout.strip().splitlines()[-1]))
        result = {
            'benchmark': 'tag_cpu',
            'study': 'normal, 256², 25 phases, SNR 20, 11 slices, 275 frames',
            'load_average': os.getloadavg(),
        }
        for name, rs in runs.items():
            result[name] = {
                k: round(statistics.median(r[k] for r in rs), 3)
                for k in ('masks_s', 'tracker_s', 'total_s')
            }
            result[name]['runs_total_s'] = [round(r['total_s'], 3) for r in rs]
        if args.baseline:
            a = pickle.loads((tmp / 'baseline0.pkl').read_bytes())
            b = pickle.loads((tmp / 'current0.pkl').read_bytes())
            result['points'] = compare(a, b)
            result['ratio_total'] = round(
                result['current']['total_s'] / result['baseline']['total_s'], 3
            )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps(result, indent=2))


if __name__ == '__main__':
    main()
