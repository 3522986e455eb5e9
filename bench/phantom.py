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
Cylinder-phantom benchmark of the meshless deformable model (paper §3.1, Fig. 4–5).

For each deformation (scaling, rotation, twisting, combination, bulge) and control fraction
(100/50/25/10/5 %): iterations to reach 0.1 mm and 0.01 mm dense RMS error (over ALL particles),
final dense RMS / max error, iterations to convergence, wall time (a separate run without the
per-iteration error callback), time to 0.1 mm and 0.01 mm (cold runs capped at those iteration
counts). Then a scaling table: seconds per iteration of the global stage and of the local stage
for N = 2k … 100k particles, the local stage's CG iteration also in CPU time per particle and per
particle–neighbour pair, and optionally (``--neighbours K``) the same sizes again with the support
radius scaled so every size has about K neighbours (the paper's ``h = 3 r̄`` gives more
neighbours at more particles: at 2k the wall holds ~3 spacings and truncates the support). One
JSON document to stdout; a Fig. 5-style PNG in ``--out``.

Usage: ``mlv-ros bench phantom [--n 5000] [--sizes 2000,5000,...] [--neighbours K] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import platform
import sys
import time

from mlv_ros.core.meshless import cylindrical_frame, MeshlessModel
from mlv_ros.core.meshless.kernel import mean_neighbour_distance, SUPPORT_FACTOR
from mlv_ros.core.sim.paper_cylinder import (
    control_subset,
    deform,
    DEFORMATIONS,
    H_CYL,
    R_INNER,
    R_OUTER,
    sample_cylinder_shell,
)
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from reference_local import PhantomSystemReference  # noqa: E402

FRACTIONS = (1.0, 0.5, 0.25, 0.1, 0.05)
SIZES = (2000, 5000, 10000, 20000, 50000, 100000)


ORDERS = ('sampled', 'morton', 'random')


def particle_order(x, order: str, seed: int = 0) -> np.ndarray:
    """
    Return a permutation of the particles ``x`` (N, 3): ``order`` one of :data:`ORDERS`.

    'sampled' keeps the sampler's lattice order (already spatially coherent), 'morton' sorts by
    the Z-order curve of a 1024³ grid over the bounding box, 'random' shuffles (the worst case
    for the sparse products' memory access).
    """
    if order == 'sampled':
        return np.arange(len(x))
    if order == 'random':
        return np.random.default_rng(seed).permutation(len(x))
    if order != 'morton':
        raise ValueError(f'order must be one of {ORDERS}, got {order!r}')
    lo = x.min(axis=0)
    q = ((x - lo) / max(float(np.ptp(x, axis=0).max()), 1e-12) * 1023).astype(np.uint64)
    code = np.zeros(len(x), dtype=np.uint64)
    for bit in range(10):
        for a in range(3):
            code |= ((q[:, a] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + a)
    return np.argsort(code, kind='stable')


def build(n: int, seed: int, support_factor: float = SUPPORT_FACTOR, order: str = 'sampled'):
    x = sample_cylinder_shell(n, seed=seed)
    x = x[particle_order(x, order, seed)]
    t0 = time.perf_counter()
    model = MeshlessModel(
        x,
        cylindrical_frame(x, [0, 0, 0], [0, 0, 1], radius=R_OUTER, half_height=H_CYL / 2),
        support_factor=support_factor,
    )
    return x, model, time.perf_counter() - t0


def support_factor_for(x, neighbours: float, sample: int = 10000, seed: int = 0) -> float:
    """
    Return the support factor ``f`` (``h_i = f r̄_i``) giving ``neighbours`` neighbours on average.

    Bisection on the mean count of particles within ``f r̄_i`` of up to ``sample`` centres (self
    excluded); regrouping of ill-shaped phyxels may add a few more in the model.
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(x)
    rbar, _ = mean_neighbour_distance(x, tree=tree)
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(x), size=min(sample, len(x)), replace=False)
    lo, hi = 1.0, 8.0
    for _ in range(30):
        f = 0.5 * (lo + hi)
        count = tree.query_ball_point(x[idx], r=f * rbar[idx], return_length=True).mean() - 1
        lo, hi = (f, hi) if count < neighbours else (lo, f)
    return 0.5 * (lo + hi)


def first_below(errs, thr):
    return next((i + 1 for i, e in enumerate(errs) if e < thr), None)


def run_case(x, model, name, fraction, seed, max_iterations):
    y = deform(x, name)
    idx = control_subset(len(x), fraction, seed=seed)
    errs = []

    def cb(_it, m):
        errs.append(float(np.sqrt(np.mean(np.sum((m.positions() - y) ** 2, axis=1)))))

    traced = model.fit(idx, y[idx], warm_start=False, max_iterations=max_iterations, callback=cb)
    err = np.linalg.norm(traced.positions - y, axis=1)
    it01, it001 = first_below(errs, 0.1), first_below(errs, 0.01)
    timed = model.fit(idx, y[idx], warm_start=False, max_iterations=max_iterations)
    t_to = {}
    for key, its in (('seconds_to_0.1mm', it01), ('seconds_to_0.01mm', it001)):
        if its is not None:
            t_to[key] = model.fit(idx, y[idx], warm_start=False, max_iterations=its).wall_time
        else:
            t_to[key] = None
    local_its = [h for h in traced.history if h['local']]
    return {
        'deformation': name,
        'control_fraction': fraction,
        'control_points': int(len(idx)),
        'particles': int(len(x)),
        'iterations_to_0.1mm': it01,
        'iterations_to_0.01mm': it001,
        'iterations': traced.iterations,
        'converged': bool(traced.converged),
        'dense_rms_mm': float(np.sqrt(np.mean(err**2))),
        'dense_max_mm': float(err.max()),
        'control_residual_rms_mm': traced.residual,
        'wall_time_s': timed.wall_time,
        **t_to,
        'local_iterations': len(local_its),
        'cg_iterations_total': int(sum(h['cg_iterations'] for h in local_its)),
        'error_trace_mm': errs,
    }


def cg_iteration_seconds(model, system_factory, iterations=10, repeats=3):
    """
    Time the local stage's CG iterations and system set-up (10 % control points).

    Returns (seconds per CG iteration, seconds to set the system up, CPU seconds per CG
    iteration), medians of ``repeats`` solves of ``iterations`` CG iterations each (wall clock;
    the CPU time, this process's, is the one to compare on a loaded machine).
    """
    model.local_operators  # noqa: B018 (built on first use, with the stiffness scale _kdiag)
    n = model.num_particles
    idx = control_subset(n, 0.1, seed=0)
    phi = model.attach(idx).weights
    pq = np.broadcast_to(np.eye(3), (len(idx), 3, 3)).copy()
    kappa = 100.0 * float(np.median(model._kdiag))
    rhs = np.random.default_rng(0).normal(size=(n, 3))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        system = system_factory((kappa, phi, pq))
        t1, c1 = time.perf_counter(), time.process_time()
        _, its = system.solve(rhs, rtol=0.0, atol=0.0, maxiter=iterations)
        its = max(its, 1)
        times.append(
            ((time.perf_counter() - t1) / its, t1 - t0, (time.process_time() - c1) / its)
        )
    return tuple(float(np.median([t[k] for t in times])) for k in range(3))


def local_stage_comparison(model):
    """
    Compare the old and the new local stage: seconds per CG iteration and per set-up.

    Old: bench/reference_local.py. Also returns the ratio old / new.
    """
    model.local_operators  # noqa: B018 (built once per model; timed in build_local_s)
    new_it, new_setup, _ = cg_iteration_seconds(model, model._local_system)
    old_it, old_setup, _ = cg_iteration_seconds(
        model, lambda d: PhantomSystemReference(model, d)
    )
    return {
        'old_s_per_cg_iteration': old_it,
        'new_s_per_cg_iteration': new_it,
        'ratio_per_cg_iteration': old_it / new_it,
        'old_setup_s': old_setup,
        'new_setup_s': new_setup,
    }


def scaling_row(
    n, seed, compare_old=False, support_factor=SUPPORT_FACTOR, fits=True, order='sampled'
):
    """
    Time one size: model build, the local stage's CG iteration and (``fits``) the two stages.

    The CG iteration also in CPU time per particle (µs) and per particle–neighbour pair (ns);
    ``order``: the particles' order (:func:`particle_order`).
    """
    x, model, t_build = build(n, seed, support_factor, order)
    t0 = time.perf_counter()
    model.local_operators  # noqa: B018
    t_local = time.perf_counter() - t0
    new_it, _, cpu_it = cg_iteration_seconds(model, model._local_system)
    row = {
        'particles': int(len(x)),
        'order': order,
        'support_factor': float(support_factor),
        'pairs': model.phyxels.num_pairs,
        'mean_neighbours': float(model.phyxels.neighbour_counts().mean()),
        'build_s': t_build,
        'build_local_s': t_local,
        's_per_cg_iteration': new_it,
        'cpu_s_per_cg_iteration': cpu_it,
        'cpu_us_per_particle_cg_iteration': 1e6 * cpu_it / len(x),
        'cpu_ns_per_pair_cg_iteration': 1e9 * cpu_it / model.phyxels.num_pairs,
    }
    if not fits:
        return row
    idx = control_subset(len(x), 0.1, seed=seed)
    y = deform(x, 'combination')
    g = model.fit(idx, y[idx], warm_start=False, local=False, max_iterations=6, tol=0.0)
    glob = [h['seconds'] for h in g.history[1:]]
    yb = deform(x, 'bulge')
    loc = model.fit(idx, yb[idx], warm_start=False, max_iterations=12, tol=0.0)
    lh = [h for h in loc.history if h['local']]
    return {
        **row,
        **({'old_vs_new': local_stage_comparison(model)} if compare_old else {}),
        'global_s_per_iteration': float(np.median(glob)),
        'local_s_per_iteration': float(np.median([h['seconds'] for h in lh])) if lh else None,
        'local_cg_iterations_median': float(np.median([h['cg_iterations'] for h in lh]))
        if lh
        else None,
        'local_s_per_cg_iteration': float(
            np.sum([h['seconds'] for h in lh]) / max(1, sum(h['cg_iterations'] for h in lh))
        )
        if lh
        else None,
    }


def linearity(rows):
    """
    Return how far a scaling series is from linear: the largest over the smallest cost per unit.

    Per particle and per particle–neighbour pair, of the CG iteration's CPU time; also the mean
    neighbour counts' range (a cost per particle grows with it at any constant cost per pair).
    """
    if len(rows) < 2:
        return None

    def spread(key):
        v = [r[key] for r in rows]
        return max(v) / min(v)

    return {
        'particles': [rows[0]['particles'], rows[-1]['particles']],
        'per_particle_max_over_min': spread('cpu_us_per_particle_cg_iteration'),
        'per_pair_max_over_min': spread('cpu_ns_per_pair_cg_iteration'),
        'mean_neighbours': [min(r['mean_neighbours'] for r in rows),
                            max(r['mean_neighbours'] for r in rows)],
    }


def plot(cases, out: Path):
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for name in DEFORMATIONS:
        rows = [c for c in cases if c['deformation'] == name]
        fr = [100 * c['control_fraction'] for c in rows]
        for ax, key in zip(axes, ('iterations_to_0.1mm', 'iterations_to_0.01mm')):
            its = [c[key] if c[key] is not None else np.nan for c in rows]
            ax.plot(fr, its, 'o-', label=name)
    for ax, thr in zip(axes, ('0.1', '0.01')):
        ax.set_xlabel('control points (% of particles)')
        ax.set_ylabel(f'iterations to {thr} mm dense RMS')
        ax.set_xscale('log')
        ax.set_xticks([5, 10, 25, 50, 100], ['5', '10', '25', '50', '100'])
        ax.grid(True, alpha=0.3)
    axes[0].axhline(40, color='grey', ls=':', lw=1)
    axes[0].axhline(160, color='grey', ls='--', lw=1)
    axes[0].set_title('Fig. 5 analogue (paper: ~40 at 100 %, ~160 at 10 %)')
    axes[1].set_title('(no point: threshold not reached)')
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / 'iterations_vs_control_fraction.png'
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return str(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--n', type=int, default=5000, help='particles for the deformation table')
    ap.add_argument('--fractions', default=','.join(str(f) for f in FRACTIONS))
    ap.add_argument(
        '--sizes', default=','.join(str(s) for s in SIZES), help="scaling table sizes ('' = skip)"
    )
    ap.add_argument(
        '--neighbours',
        type=float,
        default=0.0,
        help='also time the sizes with the support scaled to this mean neighbour count (0 = no)',
    )
    ap.add_argument(
        '--order',
        choices=ORDERS,
        default='sampled',
        help="the scaling rows' particle order (sampled: the sampler's lattice order)",
    )
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--max-iterations', type=int, default=200)
    ap.add_argument(
        '--old-up-to',
        type=int,
        default=10000,
        help='scaling rows up to this size also time the old local stage '
        '(bench/reference_local.py)',
    )
    ap.add_argument('--out', default='out/bench/phantom')
    args = ap.parse_args(argv)

    x, model, t_build = build(args.n, args.seed)
    fractions = [float(f) for f in args.fractions.split(',') if f]
    cases = []
    for name in DEFORMATIONS:
        for fr in fractions:
            cases.append(run_case(x, model, name, fr, args.seed + 1, args.max_iterations))
            print(
                f'{name} {fr}: {cases[-1]["iterations_to_0.1mm"]} its, '
                f'{cases[-1]["dense_rms_mm"]:.2e} mm, {cases[-1]["wall_time_s"]:.2f} s',
                file=sys.stderr,
            )
    local_stage = {'particles': int(len(x)), **local_stage_comparison(model)}
    for name, system in (('new', None), ('old', lambda d: PhantomSystemReference(model, d))):
        if system is not None:
            model._local_system = system
        bulge = [
            run_case(x, model, 'bulge', fr, args.seed + 1, args.max_iterations)
            for fr in (1.0, 0.1)
        ]
        model.__dict__.pop('_local_system', None)
        local_stage[f'{name}_bulge'] = [
            {
                k: c[k]
                for k in (
                    'control_fraction',
                    'dense_rms_mm',
                    'dense_max_mm',
                    'wall_time_s',
                    'cg_iterations_total',
                )
            }
            for c in bulge
        ]
    local_stage['ratio_bulge_wall_time'] = [
        o['wall_time_s'] / nw['wall_time_s']
        for o, nw in zip(local_stage['old_bulge'], local_stage['new_bulge'])
    ]
    print(f'local stage old vs new: {local_stage}', file=sys.stderr)
    scaling, fixed = [], []
    for n in [int(s) for s in args.sizes.split(',') if s]:
        scaling.append(
            scaling_row(n, args.seed, compare_old=n <= args.old_up_to, order=args.order)
        )
        print(f'scaling {n}: {scaling[-1]}', file=sys.stderr)
        if args.neighbours > 0:
            f = support_factor_for(sample_cylinder_shell(n, seed=args.seed), args.neighbours)
            fixed.append(
                scaling_row(n, args.seed, support_factor=f, fits=False, order=args.order)
            )
            print(f'scaling {n}, ~{args.neighbours:g} neighbours: {fixed[-1]}', file=sys.stderr)
    png = plot(cases, Path(args.out)) if cases else None

    fig4 = [c for c in cases if c['deformation'] != 'bulge']
    doc = {
        'benchmark': 'phantom',
        'phantom': {
            'outer_radius_mm': R_OUTER,
            'inner_radius_mm': R_INNER,
            'height_mm': H_CYL,
            'particles': int(len(x)),
            'mean_neighbours': float(model.phyxels.neighbour_counts().mean()),
            'build_s': t_build,
        },
        'solver': {
            'global': 'Gauss-Newton/LM step of eq. 15 (D = L^T P L)',
            'local': 'block-Jacobi PCG on (kappa Phi^T P Phi + K_lin + fit-error penalty) '
            'after the global stage settles (mlv_ros.core.meshless.local)',
            'data_weight': 100.0,
            'youngs_modulus': 1.0,
            'poisson_ratio': 0.45,
        },
        'machine': {
            'cpus': os.cpu_count(),
            'platform': platform.platform(),
            'loadavg_1min': os.getloadavg()[0] if hasattr(os, 'getloadavg') else None,
        },
        'cases': cases,
        'local_stage_old_vs_new': local_stage,
        'scaling': scaling,
        'scaling_linearity': linearity(scaling),
        'scaling_fixed_neighbours': fixed,
        'scaling_fixed_neighbours_linearity': linearity(fixed),
        'targets': {
            'fig4_below_0.1mm_within_5s': all(
                c['dense_rms_mm'] < 0.1 and c['wall_time_s'] < 5 for c in fig4
            ),
            'fig4_max_iterations_to_0.1mm_at_100pct': max(
                (
                    (c['iterations_to_0.1mm'] or 10**9)
                    for c in fig4
                    if c['control_fraction'] == 1.0
                ),
                default=None,
            ),
            'fig4_max_iterations_to_0.1mm_at_10pct': max(
                (c['iterations_to_0.1mm'] or 10**9) for c in fig4 if c['control_fraction'] == 0.1
            )
            if any(c['control_fraction'] == 0.1 for c in fig4)
            else None,
            'fig4_max_seconds_to_0.01mm': max(
                (c['seconds_to_0.01mm'] or float('inf')) for c in fig4
            )
            if fig4
            else None,
        },
        'png': png,
    }
    json.dump(doc, sys.stdout, indent=1)
    sys.stdout.write('\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
