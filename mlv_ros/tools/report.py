"""``mlv-ros report RUN.mcap [--compare OTHER.mcap]``: the motion report of a recorded run,
rebuilt from the recording alone (no tracking is recomputed): PNG figures in the spirit of the
paper's Fig. 9–16, a bull's-eye of peak strain by AHA segment, ``summary.json`` and an
``index.html`` that shows them together."""

from __future__ import annotations

import sys
from pathlib import Path


def add_arguments(parser):
    parser.add_argument("mcap", help="recorded run (RUN_DIR/run.mcap or the run directory)")
    parser.add_argument("--compare", help="a second recorded run shown side by side (e.g. hypertrophic)")
    parser.add_argument("--out", help="report directory (default: RUN_DIR/report)")
    parser.add_argument("--label", default=None, help="name of the run (default: its directory name)")
    parser.add_argument("--compare-label", default=None, help="name of the comparison run")


def load_run_data(path: Path, label: str):
    """RunData (per-phase metrics, ED and per-phase positions, LV frame) from a recording."""
    from mlv_ros.core.analysis import LVFrame, PhaseMetrics
    from mlv_ros.core.report.summary import RunData
    from mlv_ros.core.tracking import lv_frame_axes
    from mlv_ros.tools.run import read_run

    run = read_run(path)
    frame = None
    if run["ed"] is not None and run["rotation"] is not None:
        frame = LVFrame(*lv_frame_axes(run["ed"], run["rotation"]))
    phases = [PhaseMetrics.from_dict(d) for _, d in sorted(run["metrics"].items())]
    return RunData(phases, run["ed"], run["positions"] or None, frame, label), run


def build(mcap: Path, out: Path | None = None, compare: Path | None = None, label: str | None = None,
          compare_label: str | None = None) -> Path:
    from mlv_ros.core.report import build_report

    mcap = Path(mcap)
    run_dir = mcap if mcap.is_dir() else mcap.parent
    data, raw = load_run_data(mcap, label or run_dir.name)
    other = None
    if compare:
        cpath = Path(compare)
        other, _ = load_run_data(cpath, compare_label or (cpath if cpath.is_dir() else cpath.parent).name)
    missing = []
    if not data.phases:
        missing.append("no /lv/metrics in the recording")
    if data.ed_positions is None:
        missing.append("no registered model (/mlv/registered_cloud) in the recording")
    meta = {"title": f"LV motion — {data.label}", "label": data.label, "source": str(mcap),
            "frames_recorded": raw["frames"], "phases_with_metrics": len(data.phases),
            "missing": missing}
    if other is not None:
        meta["compare_label"] = other.label
    return build_report(out or run_dir / "report", data.phases, data.ed_positions, data.positions_by_phase,
                        compare=other, meta=meta, frame=data.frame)


def run(args) -> int:
    try:
        index = build(Path(args.mcap), Path(args.out) if args.out else None,
                      Path(args.compare) if args.compare else None, args.label, args.compare_label)
    except (FileNotFoundError, ValueError) as exc:
        print(f"mlv-ros report: {exc}", file=sys.stderr)
        return 2
    print(index)
    return 0
