"""A randomized acquisition protocol through the real DICOM path and the whole graph, against the
study's analytic ground truth (``mlv-ros simulate --random`` + ``mlv-ros run --dicom``).

Seed 502 draws a hypertrophic LV at an oblique axis, a grid at 58° to the image axes, 1.43 mm
pixels, 12 SA + 4 LA planes, tagged surroundings; the test fixes 16 phases to keep it short.
The robustness bench (``mlv-ros bench robustness``, seeds from 1000) covers the space; this is the
part of it that must never regress in ``make test``.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from mlv_ros.tools.run import groundtruth_accuracy, run_graph

BIN = Path(sys.executable).parent
SEED = 502


@pytest.fixture(scope="module")
def random_study_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("random")
    study = root / "study"
    subprocess.run([str(BIN / "mlv-ros"), "simulate", "--random", str(SEED), "--phases", "16", "--out", str(study),
                    "--no-progress"], check=True, capture_output=True, text=True, timeout=300)
    summary = run_graph({"source": "dicom", "path": str(study / "dicom")}, root / "run",
                        overrides={"registration": {"num_particles": 1500}}, timeout=400,
                        progress=lambda *_: None)
    return study, summary


def test_random_protocol_every_phase_solved(random_study_run):
    study, summary = random_study_run
    protocol = (study / "protocol.yaml").read_text()
    assert summary["complete"], summary
    assert summary["phases_solved"] == summary["num_phases"] == 16
    # The drawn protocol is not ours: oblique grid, not the default matrix.
    assert "tag_angle_deg: 58.36" in protocol


def test_random_protocol_accuracy_against_ground_truth(random_study_run):
    study, summary = random_study_run
    acc = groundtruth_accuracy(Path(summary["mcap"]), study)
    es = acc["es"]
    # The must-criteria at end-systole.
    assert es["median_mm"] <= 1.0 and es["p95_mm"] <= 2.5, json.dumps(es)
    assert es["twist_error_deg"] <= 2.0, json.dumps(es)
    assert acc["inside_myocardium"] >= 0.9 and acc["coverage"] >= 0.9, (acc["inside_myocardium"], acc["coverage"])
    assert max(r["median_mm"] for r in acc["per_phase"]) <= 1.0
