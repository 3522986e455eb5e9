"""``mlv-ros demo`` (the README's ``make demo``): simulate the built-in ``normal`` LV phantom
(8 SA + 3 LA tagged cines, 256², 25 phases, SNR 20), run the whole graph on it in one process,
record the run, build the report and print the accuracy against the phantom's analytic ground
truth. About a minute and a half on 2 cores."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def add_arguments(parser):
    parser.add_argument("--out", default=None, help="run directory (default: runs/demo-<date-time>)")
    parser.add_argument("--preset", default="normal", help="phantom preset (default: normal)")


def run(args) -> int:
    from mlv_ros.tools.report import build
    from mlv_ros.tools.run import phantom_accuracy, run_graph

    out = Path(args.out or f"runs/demo-{time.strftime('%Y%m%d-%H%M%S')}")
    print(f"[demo] simulating the '{args.preset}' phantom and running the graph -> {out}", file=sys.stderr)
    try:
        summary = run_graph({"source": "phantom", "preset": args.preset}, out,
                            progress=lambda s: print(s, file=sys.stderr))
    except (FileExistsError, ValueError) as exc:
        print(f"mlv-ros demo: {exc}", file=sys.stderr)
        return 2
    if not summary["complete"]:
        print(json.dumps(summary, indent=2))
        print("mlv-ros demo: the run did not complete; see /diagnostics in the recording", file=sys.stderr)
        return 1
    acc = phantom_accuracy(Path(summary["mcap"]), args.preset, summary["num_phases"])
    index = build(Path(summary["mcap"]))
    es = acc["es"]
    result = {
        "run_dir": str(out), "recording": summary["mcap"], "report": str(index),
        "seconds": summary["seconds"], "frames": summary["frames_published"], "phases": summary["num_phases"],
        "messages_recorded": summary["recorded_messages"],
        "accuracy_at_end_systole": {
            "phase": es["phase"], "median_3d_error_mm": round(es["median_mm"], 3),
            "p95_3d_error_mm": round(es["p95_mm"], 3), "max_twist_error_deg": round(es.get("twist_error_deg", float("nan")), 2),
            "max_radius_error_mm": round(es.get("radius_error_mm", float("nan")), 2)},
        "worst_phase_median_mm": round(max(r["median_mm"] for r in acc["per_phase"]), 3),
        "particles_inside_true_myocardium": round(acc["inside_myocardium"], 4),
        "true_myocardium_covered": round(acc["coverage"], 4),
    }
    (out / "accuracy.json").write_text(json.dumps(acc, indent=2))
    print(json.dumps(result, indent=2))
    return 0
