"""The local stage of :mod:`mlv_ros.core.meshless.local` against the reference copies of the
stages it replaced (``bench/reference_local.py``): same operator, same solutions."""

import sys
from pathlib import Path

import numpy as np
import pytest

from mlv_ros.core import tracking
from mlv_ros.core.meshless import MeshlessModel, cylindrical_frame, elastic
from mlv_ros.core.phantom import H_CYL, R_OUTER, control_subset, deform, sample_cylinder_shell
from mlv_ros.core.sim import simulate_study
from test_tracking import observed, referenced_tracker

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from reference_local import PhantomSystemReference  # noqa: E402, I100
from reference_local import tracker_fit_error_matrix, tracker_local_solve  # noqa: E402, I100


@pytest.fixture(scope="module")
def study():
    return simulate_study("normal", snr=20, quick=True)


def test_operators_equal_the_assembled_fit_error_and_matrix_free_stiffness(study):
    _, tr, _ = referenced_tracker(study, n=800)
    m, rng = tr.model, np.random.default_rng(0)
    L = tracker_fit_error_matrix(m)
    np.testing.assert_allclose(tr._local.fit_error_diagonal, L.diagonal(), rtol=1e-10)
    system = tr._local.system(fit_error=2.0, eps=0.5)
    for u in (rng.normal(size=(tr.num_particles, 3)), np.sin(tr.rest / 15.0)):  # rough and smooth
        ref = elastic.linear_stiffness_apply(m.operator, u, m.phyxels.volume, m.lam, m.mu) + 2.0 * (L @ u) + 0.5 * u
        np.testing.assert_allclose(system.internal(u), ref, atol=1e-9 * np.abs(ref).max())
    # the paper model's stabilisation is the same penalty with other weights
    coef = m.stabilisation * m.mu * elastic.stabilisation_weights(m.operator, m.phyxels.volume)
    u = rng.normal(size=(tr.num_particles, 3))
    ref = elastic.stabilisation_apply(m.operator, u, coef)
    np.testing.assert_allclose(m.stabilisation * m.mu * m.local_operators.fit_error_apply(u), ref,
                               atol=1e-9 * np.abs(ref).max())


def test_tracker_local_stage_matches_the_reference_on_simulated_tags(study, monkeypatch):
    """Every local solve of three phases (two slice-following passes each) against the old one on
    the same tag points, global fit and warm start: CG at rtol 1e-3 either way."""
    m = study.motion
    X, tr, refs = referenced_tracker(study, n=1500)
    new_solve, cache, diffs = tracking.MotionTracker._local_solve, {}, []

    tr.cg_rtol_following = tr.cg_rtol  # every pass at the reference's tolerance

    def both(self, phi, targets, normals, x_global, weights=None, rtol=None):
        # The reference has no data weights: these tags all have confidence 1, so equal weights.
        assert weights is None or np.ptp(weights) == 0
        d0 = None if self.delta is None else self.delta.copy()
        new = new_solve(self, phi, targets, normals, x_global, weights, rtol)
        old, _ = tracker_local_solve(self, phi, targets, normals, x_global, d0, cache)
        diffs.append(np.linalg.norm(new - old, axis=1))
        return new

    monkeypatch.setattr(tracking.MotionTracker, "_local_solve", both)
    for phase in (1, 2, int(round(m.es_phase))):
        tr.solve(phase, observed(study, refs, phase), m.num_phases)
    assert len(diffs) == 6
    assert max(np.median(d) for d in diffs) < 0.02, [np.median(d) for d in diffs]
    assert max(np.percentile(d, 95) for d in diffs) < 0.1, [np.percentile(d, 95) for d in diffs]


def test_paper_model_fit_matches_the_reference_local_stage():
    x = sample_cylinder_shell(1500, seed=0)
    model = MeshlessModel(x, cylindrical_frame(x, [0, 0, 0], [0, 0, 1], radius=R_OUTER, half_height=H_CYL / 2))
    idx = control_subset(len(x), 0.1, seed=1)
    y = deform(x, "bulge")
    new = model.fit(idx, y[idx], warm_start=False, max_iterations=60)
    model._local_system = lambda data: PhantomSystemReference(model, data)
    old = model.fit(idx, y[idx], warm_start=False, max_iterations=60)
    rms_new, rms_old = (float(np.sqrt(np.mean(np.sum((r.positions - y) ** 2, axis=1)))) for r in (new, old))
    assert abs(rms_new - rms_old) < 1e-3, (rms_new, rms_old)
    assert np.median(np.linalg.norm(new.positions - old.positions, axis=1)) < 0.02
