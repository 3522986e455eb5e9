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
Regenerate the sample acquisition in this folder (``normal_sample.mcap``).

The `normal` phantom (seed 0, SNR 20, 128², 16 phases, 8 SA + 3 LA slices) written to DICOM, read
back by the DICOM reader and recorded as ``/mlv/frames`` messages (uint16, as the DICOM stores
them) to ``normal_sample.mcap``.

    .venv/bin/python bags/make_sample.py [--dicom-out DIR]
"""

import argparse
from pathlib import Path
import tempfile
import time

from mlv_ros import bagio, conversions, qos
from mlv_ros.core.io.dicom import read_dicom_dir, write_study_dicom
from mlv_ros.core.sim import simulate_study
from mlv_ros.nodes.frame_source import count_slices, order_frames
from rclpy.serialization import serialize_message

SAMPLE = {'preset': 'normal', 'snr': 20.0, 'size': 128, 'num_phases': 16, 'seed': 0}
HERE = Path(__file__).resolve().parent


def sample_dicom(out_dir: Path) -> Path:
    """Write the sample study's DICOM files under ``out_dir`` (deterministic)."""
    study = simulate_study(
        SAMPLE['preset'],
        snr=SAMPLE['snr'],
        size=SAMPLE['size'],
        num_phases=SAMPLE['num_phases'],
        seed=SAMPLE['seed'],
    )
    write_study_dicom(study, out_dir)
    return out_dir


def sample_frames(dicom_dir: Path):
    frames, problems = read_dicom_dir(dicom_dir)
    if problems:
        raise ValueError(f'unexpected DICOM problems: {problems}')
    return order_frames(count_slices(frames), 'slice_major')


def main():
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--dicom-out', help='keep the DICOM files here (default: a temporary folder)')
    ap.add_argument('--out', default=str(HERE / 'normal_sample.mcap'))
    args = ap.parse_args()
    dicom = Path(args.dicom_out or tempfile.mkdtemp(prefix='mlv-sample-dicom-'))
    frames = sample_frames(sample_dicom(dicom))
    out = Path(args.out)
    if out.exists():
        out.unlink()
    writer = bagio.BagWriter(out, compression='zstd')
    writer.add_topic(qos.FRAMES, qos.TOPIC_TYPES[qos.FRAMES], [qos.qos_dict(qos.stream_qos())])
    t0 = time.time_ns()
    for i, f in enumerate(frames):
        stamp = t0 + i * 10_000_000  # 10 ms apart, slice-major as acquired
        writer.write(
            qos.FRAMES, serialize_message(conversions.frame_to_msg(f, stamp=stamp * 1e-9)), stamp
        )
    writer.close()
    (out.parent / 'metadata.yaml').unlink()  # several bags share this folder: no per-bag metadata
    print(f'{out}: {len(frames)} frames, {out.stat().st_size / 1e6:.1f} MB (DICOM in {dicom})')


if __name__ == '__main__':
    main()
