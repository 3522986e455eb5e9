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
Benchmark: the whole graph on the default study as ``mlv-ros run`` runs it.

The default study: normal phantom, 8 SA + 3 LA, 256², 25 phases, SNR 20; the tag detector in a
child process and the phantom simulated in another (MLV_ROS_ONE_PROCESS=1: all in one). Prints
one JSON document: total time, per-stage latency per phase (from the recording's receive times),
peak RSS (and RSS / PSS / USS summed over the processes, sampled: ``bench/_memory.py``),
messages published vs recorded, accuracy; then ``local_stage``: the run's recorded tag
points replayed through a tracker built as the solver node builds it, every local solve timed
with the new stage and with the old one (``bench/reference_local.py``) on identical inputs
(``--no-replay`` skips it).

    mlv-ros bench pipeline [-- --phases 25 --size 256 --out DIR]
"""

import argparse
import contextlib
import json
from pathlib import Path
import resource
import statistics
import sys
import tempfile
import time
from types import SimpleNamespace

from mlv_msgs.msg import ModelState, MotionMetrics, TaggedFrame, TagPoints
from mlv_ros import bagio, conversions, qos
from mlv_ros.core.meshless import local as local_module
from mlv_ros.core.tracking import MotionTracker
from mlv_ros.recording import phantom_accuracy
from mlv_ros.runner import run_graph
from mlv_ros.threads import compute_threads
import numpy as np
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _memory import TreeMemory  # noqa: E402, I100
from reference_local import tracker_local_solve  # noqa: E402


def stage_latencies(mcap: Path) -> dict:
    """
    Return per-phase latencies (ms) from receive times in the recording.

    Frame → tag points (per frame), last tag points of a phase → its motion (solver), motion →
    metrics (analyzer).
    """
    frame_t, tag_t, motion_t, metrics_t = {}, {}, {}, {}
    for m in bagio.read_bag(
        mcap, topics=[qos.FRAMES, qos.TAG_POINTS, qos.MODEL_STATE, qos.METRICS]
    ):
        if m.topic == qos.FRAMES:
            f = bagio.deserialize(m.data, TaggedFrame, m.missing)
            frame_t[(f.view, f.slice_index, f.phase_index)] = m.log_time_ns
        elif m.topic == qos.TAG_POINTS:
            p = deserialize_message(m.data, TagPoints)
            tag_t[(p.view, p.slice_index, p.phase_index)] = m.log_time_ns
        elif m.topic == qos.MODEL_STATE:
            motion_t[deserialize_message(m.data, ModelState).phase_index] = m.log_time_ns
        else:
            metrics_t[deserialize_message(m.data, MotionMetrics).phase_index] = m.log_time_ns
    tag_ms = [(tag_t[k] - frame_t[k]) / 1e6 for k in tag_t if k in frame_t]
    solve_ms = {}
    for ph, t in motion_t.items():
        last_tag = max((v for k, v in tag_t.items() if k[2] == ph), default=None)
        if last_tag is not None and ph > 0:
            solve_ms[ph] = (t - last_tag) / 1e6
    analyse_ms = [(metrics_t[ph] - t) / 1e6 for ph, t in motion_t.items() if ph in metrics_t]

    def stats(v):
        return (
            {'median': round(statistics.median(v), 1), 'max': round(max(v), 1), 'n': len(v)}
            if v
            else {}
        )

    return {
        'tag_detector_per_frame_ms': stats(tag_ms),
        'solver_per_phase_ms': stats(list(solve_ms.values())),
        # the first solved phase: its last tag points → its motion, model build waits included
        'solver_first_phase_ms': round(solve_ms[min(solve_ms)], 1) if solve_ms else None,
        'analyzer_per_phase_ms': stats(analyse_ms),
    }


class CpuSplit:
    """
    Process time per part of a phase's solve, each part exclusive of the parts it calls.

    ``wrap(owner, name, part)`` replaces ``owner.name`` by a timed copy (:meth:`restore` puts the
    originals back); :meth:`take` returns the seconds per part since the last call and starts
    again. The part ``None`` is timed only to be left out of its callers (the reference stage the
    replay runs beside the solver).
    """

    def __init__(self):
        self.seconds: dict = {}
        self._stack: list = []
        self._wrapped: list = []

    def wrap(self, owner, name: str, part):
        """Time ``owner.name`` (a function or bound method) as ``part``."""
        inner = getattr(owner, name)

        def timed(*args, **kwargs):
            t0 = time.process_time()
            self._stack.append(0.0)
            try:
                return inner(*args, **kwargs)
            finally:
                spent = time.process_time() - t0
                nested = self._stack.pop()
                if part is not None:
                    self.seconds[part] = self.seconds.get(part, 0.0) + spent - nested
                if self._stack:
                    self._stack[-1] += spent

        self._wrapped.append((owner, name, name in vars(owner), inner))
        setattr(owner, name, timed)
        return timed

    def restore(self):
        """Put back every wrapped attribute, last wrapped first."""
        for owner, name, own, inner in reversed(self._wrapped):
            if own:
                setattr(owner, name, inner)
            else:  # a bound method: the instance's copy shadowed its class's function
                delattr(owner, name)
        self._wrapped.clear()

    def take(self) -> dict:
        """Return the seconds per part since the last call, and reset them."""
        out, self.seconds = self.seconds, {}
        return out


def split_tracker(tr: MotionTracker) -> CpuSplit:
    """
    Time a tracker's solve by part.

    Parts: ``cg`` (PCG iterations), ``cg_start`` (the right-hand side and CG's first residual,
    :meth:`LocalSystem.right_hand_side`), ``local_setup`` (the system: tangents, blocks, coarse
    factor), ``local_other`` (the rest of a local solve), ``attach`` (control-point weights and
    the inside test), ``global_fit``, ``twist``, ``follow`` (slice following), ``outliers``,
    ``coupling`` and ``other`` (the rest of :meth:`MotionTracker.solve`).
    """
    split = CpuSplit()
    split.wrap(local_module, 'pcg', 'cg')
    split.wrap(local_module.LocalSystem, 'right_hand_side', 'cg_start')
    split.wrap(tr._local, 'system', 'local_setup')
    for name, part in (
        ('_local_solve', 'local_other'),
        ('_attach', 'attach'),
        ('_fit_global', 'global_fit'),
        ('_twist_function', 'twist'),
        ('_follow_slices', 'follow'),
        ('_outliers', 'outliers'),
        ('_coupled_axial', 'coupling'),
        ('_outward_points', 'coupling'),
        ('solve', 'other'),
    ):
        split.wrap(tr, name, part)
    split.wrap(tr.model, 'attach', 'attach')
    return split


def recorded_solver_input(mcap: Path) -> tuple:
    """
    Return what a run's solver took: the registered cloud, the registration and the tag points.

    Returns
    -------
    cloud : ndarray
        The registered particle cloud (:func:`mlv_ros.conversions.msg_to_cloud`).
    state : ModelState
        The registration's global state, or None if the run has none.
    sets : dict
        Phase → (view, slice) → TagPointSet.

    """
    cloud = state = None
    sets: dict = {}
    for m in bagio.read_bag(
        mcap, topics=[qos.REGISTERED_CLOUD, qos.REGISTERED_STATE, qos.TAG_POINTS]
    ):
        if m.topic == qos.REGISTERED_CLOUD:
            cloud = conversions.msg_to_cloud(deserialize_message(m.data, PointCloud2))
        elif m.topic == qos.REGISTERED_STATE:
            state = conversions.msg_to_model_state(deserialize_message(m.data, ModelState))
        else:
            p = conversions.msg_to_tagpoints(deserialize_message(m.data, TagPoints))
            sets.setdefault(int(p.phase_index), {})[(int(p.view), int(p.slice_index))] = p
    return cloud, state, sets


def recorded_tracker(cloud, state, ed_sets=None, tracker_class=MotionTracker, **options):
    """
    Build a tracker on a run's registration as the solver node builds it.

    Parameters
    ----------
    cloud, state :
        The registered cloud and global state (:func:`recorded_solver_input`).
    ed_sets : dict, optional
        (view, slice) → the ED TagPointSet, each set as a reference; default none.
    tracker_class : type
        ``MotionTracker``, or another source tree's (``bench/solver_pair.py``).
    **options
        MotionTracker keywords.

    Returns
    -------
    MotionTracker
        The tracker.

    """
    tr = tracker_class(
        conversions.xyz(cloud),
        state.translation,
        state.rotation,
        polar=(cloud['alpha'], cloud['beta'], cloud['w']),
        shape=(state.a0, state.a1, state.a2, state.a3, state.tau),
        **options,
    )
    for pts in (ed_sets or {}).values():
        tr.set_reference(pts)
    return tr


def local_stage_replay(mcap: Path) -> dict:
    """
    Old vs new local stage on the run's recorded tag points (seconds; medians over the solves).

    The tracker is built from the recorded registration with the solver node's default
    parameters; each phase is solved as the node solves it, and every call of the local stage
    also runs the reference copy of the old one from the same warm start (its time is left out of
    the new solver's per-phase time). The old stage's first call includes its fit-error matrix.
    """
    cloud, state, sets = recorded_solver_input(mcap)
    t0 = time.perf_counter()
    tr = recorded_tracker(cloud, state)
    build_s = time.perf_counter() - t0
    for pts in sets.get(0, {}).values():
        tr.set_reference(pts)
    split = split_tracker(tr)
    reference = SimpleNamespace(solve=tracker_local_solve)
    split.wrap(reference, 'solve', None)  # left out of the split
    new_solve, cache, calls = tr._local_solve, {}, []

    def both(phi, targets, normals, x_global, weights=None, rtol=None, scale=None):
        # The reference has no per-point weights (confidence, slice noise): where a phase has
        # them, the two differ by that as well.
        d0 = None if tr.delta is None else tr.delta.copy()
        t1 = time.perf_counter()
        new = new_solve(phi, targets, normals, x_global, weights, rtol, scale)
        t2 = time.perf_counter()
        kept, tr.cg_rtol = (
            tr.cg_rtol,
            tr.cg_rtol if rtol is None else rtol,
        )  # the reference at the same tolerance
        old, _ = reference.solve(tr, phi, targets, normals, x_global, d0, cache)
        tr.cg_rtol = kept
        calls.append(
            (
                t2 - t1,
                time.perf_counter() - t2,
                float(np.median(np.linalg.norm(new - old, axis=1))),
            )
        )
        return new

    tr._local_solve = both
    phase_s, phase_its, phase_cpu, num_phases = [], [], [], max(sets) + 1
    for p in sorted(sets)[1:]:
        before = len(calls)
        tr.cg_iterations.clear()
        split.take()
        t1 = time.perf_counter()
        tr.solve(p, sets[p], num_phases)
        phase_its.append(sum(tr.cg_iterations))
        phase_s.append(time.perf_counter() - t1 - sum(c[1] for c in calls[before:]))
        phase_cpu.append(split.take())
    split.restore()
    new_t, old_t, diff = (np.array(v) for v in zip(*calls))
    later = phase_cpu[1:] or phase_cpu  # the first phase also builds what later phases reuse
    parts = sorted({k for d in later for k in d})
    return {
        'particles': tr.num_particles,
        'phases': len(phase_s),
        'local_solves': len(calls),
        'model_build_s': round(build_s, 3),
        'first_phase_s': round(phase_s[0], 3),
        'solver_per_phase_s_median': round(float(np.median(phase_s)), 3),
        'cg_iterations_per_phase_median': float(np.median(phase_its)),
        # process time (CPU) per phase after the first, the median of each part and of the sum
        'solver_cpu_per_phase_ms_median': round(
            1e3 * float(np.median([sum(d.values()) for d in later])), 1
        ),
        'solver_cpu_split_ms_median': {
            k: round(1e3 * float(np.median([d.get(k, 0.0) for d in later])), 1) for k in parts
        },
        'new_local_s_median': round(float(np.median(new_t)), 4),
        'old_local_s_median': round(float(np.median(old_t[1:])), 4),
        'ratio_local_median': round(float(np.median(old_t[1:]) / np.median(new_t)), 2),
        'old_first_local_s_with_matrix_build': round(float(old_t[0]), 3),
        'position_difference_mm_median': round(float(np.median(diff)), 4),
        'position_difference_mm_worst_solve': round(float(diff.max()), 4),
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--phases', type=int, default=25)
    ap.add_argument('--size', type=int, default=256)
    ap.add_argument('--preset', default='normal')
    ap.add_argument('--out', default=None)
    ap.add_argument(
        '--no-replay', action='store_true', help='skip the old-vs-new local stage replay'
    )
    ap.add_argument(
        '--memory-period-s',
        type=float,
        default=0.1,
        help='sample the RSS/PSS/USS of this process and its children this often (0 = off)',
    )
    args = ap.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix='mlv-bench-pipeline-'))
    memory = TreeMemory(period_s=args.memory_period_s) if args.memory_period_s > 0 else None
    t0 = time.perf_counter()
    with memory or contextlib.nullcontext():
        s = run_graph(
            {
                'source': 'phantom',
                'preset': args.preset,
                'size': args.size,
                'num_phases': args.phases,
            },
            out,
            progress=lambda *_: None,
        )
    wall = time.perf_counter() - t0
    topics = bagio.bag_topics(out / 'run.mcap')
    acc = phantom_accuracy(out / 'run.mcap', args.preset, args.phases) if s['complete'] else {}
    published = {
        qos.FRAMES: s['frames_published'],
        qos.TAG_POINTS: s['tag_sets_published'],
        qos.MOTION: s['phases_solved'],
        qos.MODEL_STATE: s['phases_solved'],
        qos.METRICS: s['metrics_published'],
    }
    result = {
        'benchmark': 'pipeline',
        'preset': args.preset,
        'size': args.size,
        'phases': args.phases,
        'slices': 11,
        'total_s': round(wall, 2),
        'graph_s': s['seconds'],
        'peak_rss_mb': round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        # the largest of the run's child processes (the tag detector's: mlv_ros.graph_process;
        # the phantom's mlv_ros.render_process peaks at ~105 MB)
        'peak_rss_mb_child_process': round(
            resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, 1
        ),
        # RSS / PSS / USS summed over the run's processes at one instant (bench/_memory.py)
        'memory': memory.result() if memory is not None else None,
        'latency': stage_latencies(out / 'run.mcap'),
        'published_vs_recorded': {
            t: [published[t], topics.get(t, {}).get('count', 0)] for t in published
        },
        'all_recorded': all(published[t] == topics.get(t, {}).get('count', 0) for t in published),
        'accuracy_es': acc.get('es'),
        'complete': s['complete'],
        'run_dir': str(out),
    }
    if not args.no_replay and s['complete']:
        with compute_threads():  # one BLAS/OpenMP thread, as every graph process runs
            result['local_stage'] = local_stage_replay(out / 'run.mcap')
    print(json.dumps(result, indent=2))


if __name__ == '__main__':
    main()
