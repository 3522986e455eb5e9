"""``mlv-ros simulate``: write a simulated tagged-MRI study (DICOM + ground truth)."""

from __future__ import annotations

import sys
from pathlib import Path


def add_arguments(parser):
    parser.add_argument("--preset", default="normal",
                        help="normal | hypertrophic | infarct | cylinder, or a preset YAML path")
    parser.add_argument("--out", required=True, type=Path,
                        help="output directory (DICOM under OUT/dicom, ground truth in OUT)")
    parser.add_argument("--snr", type=float, default=None,
                        help="myocardium / noise sigma (default: the preset's, 20); 0 = noiseless")
    parser.add_argument("--size", type=int, default=None, help="rows = columns (default 256)")
    parser.add_argument("--phases", type=int, default=None, help="phases per cycle (default 25)")
    parser.add_argument("--subplanes", type=int, default=None,
                        help="through-slice sub-planes (default 5)")
    parser.add_argument("--seed", type=int, default=0, help="noise and UID seed")
    parser.add_argument("--points", type=int, default=2000,
                        help="material points with stored trajectories")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def run(args) -> int:
    from tqdm import tqdm

    from mlv_ros.core.io import write_groundtruth, write_study_dicom
    from mlv_ros.core.sim import load_preset, simulate_study

    try:
        preset = load_preset(args.preset)
    except (FileNotFoundError, ValueError) as exc:
        print(f"mlv-ros simulate: {exc}", file=sys.stderr)
        return 2
    snr = preset["imaging"]["snr"] if args.snr is None else args.snr
    snr = None if snr == 0 else snr
    bar = tqdm(total=1, unit="img", desc=f"simulate {preset['name']}", disable=args.no_progress)

    def progress(done, total):
        bar.total = total
        bar.update(done - bar.n)

    try:
        study = simulate_study(preset, snr=snr, size=args.size, num_phases=args.phases,
                               seed=args.seed, subplanes=args.subplanes, progress=progress)
    except ValueError as exc:
        bar.close()
        print(f"mlv-ros simulate: {exc}", file=sys.stderr)
        return 2
    bar.close()
    out = Path(args.out)
    wbar = tqdm(total=len(study.frames), unit="file", desc="write DICOM", disable=args.no_progress)
    files = write_study_dicom(study, out / "dicom",
                              progress=lambda done, total: wbar.update(done - wbar.n))
    wbar.close()
    jpath, npath = write_groundtruth(study, out, n_points=args.points)
    print(f"wrote {len(files)} DICOM files to {out / 'dicom'}; ground truth {jpath.name}, {npath.name}")
    return 0
