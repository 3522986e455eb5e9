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
Reliability benchmark: `mlv-ros bench reliability` prints one JSON document.

- ``dicom_corpus``: the DICOM bad-input corpus beside a valid study through ``read_dicom_dir``:
  cases tried, reported as expected, exceptions escaping the reader (crashes, must be 0), valid
  frames lost (0).
- ``message_corpus``: the message corpus fed into the live in-process graph among a valid study
  (``test/graphkit.feed_corpus``): cases reported by the consuming node, crashes (exceptions out of
  a callback, 0), nodes down after the corpus (0), false alarms on valid frames, phases analysed.
- ``load``: a whole study published at once, slice-major, into the graph and a recorder: frames
  in vs out at every stage (``frames_lost`` must be 0).
- ``slow_subscriber``: a burst of frames beyond the recorder's queue before it can take any:
  published = recorded + reported lost (never silent).
- ``sigterm``: a recorder process stopped by SIGTERM while frames stream in: messages it received
  vs messages in the file (equal), and the file readable by rosbags.
- ``sigkill``: a recorder process SIGKILLed mid-stream: completed chunks readable, messages
  ``mlv-ros recover`` rewrites.

Options: ``--quick`` (smaller studies), ``--repeat N`` (repeat the timing-sensitive sections).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import tempfile
import time

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test'))

from conftest import spin_until  # noqa: E402  (claims a private ROS domain for this process)


def _script(name: str) -> str:
    return str(Path(sys.prefix) / 'bin' / name)


def dicom_corpus(tmp: Path) -> dict:
    from corpus.dicom_cases import frames_by_path, write_dicom_corpus
    from mlv_ros.core.io import read_dicom_dir, write_study_dicom
    from mlv_ros.core.sim import simulate_study

    study = simulate_study('normal', snr=20.0, size=48, num_phases=3, subplanes=1, seed=2)
    good = write_study_dicom(study, tmp / 'dicom' / 'a_valid')
    cases = write_dicom_corpus(tmp / 'dicom' / 'b_corpus', good)
    t0 = time.monotonic()
    crashes = []
    try:
        res = read_dicom_dir(tmp / 'dicom')
    except Exception as exc:  # the reader must report per file, never raise for one bad file
        crashes.append(f'{type(exc).__name__}: {exc}')
        return {'cases': len(cases), 'crashes': len(crashes), 'errors': crashes}
    seconds = time.monotonic() - t0
    why, loaded = dict(res.problems), frames_by_path(res)
    as_expected = 0
    for c in cases:
        files = list(map(str, c.files))
        if c.outcome == 'error':
            as_expected += all(c.expect in why.get(f, '').lower() for f in files)
        else:
            as_expected += all(f in loaded for f in files)
    return {
        'cases': len(cases),
        'as_expected': as_expected,
        'crashes': 0,
        'valid_frames_lost': sum(str(p) not in loaded for p in good),
        'read_s': round(seconds, 2),
    }


def message_corpus(num_phases: int) -> dict:
    from corpus.message_cases import message_cases
    from graphkit import feed_corpus, graph_nodes, Probe, wait_matched
    from mlv_ros import conversions, qos
    from mlv_ros.core.sim import simulate_study
    from mlv_ros.nodes.frame_source import count_slices, order_frames
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    frames = order_frames(
        count_slices(
            list(simulate_study('normal', snr=20, quick=True, num_phases=num_phases).frames)
        ),
        'slice_major',
    )
    valid = [conversions.frame_to_msg(f, stamp=1.0 + i) for i, f in enumerate(frames)]
    max_pixels = 256 * 256
    cases = message_cases(valid, stamp0=1000.0, max_pixels=max_pixels)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    nodes = graph_nodes(ctx, max_pixels=max_pixels)
    probe = Probe(ctx)
    try:
        for n in (*nodes.values(), probe):
            ex.add_node(n)
        wait_matched(
            ex,
            probe,
            {
                qos.FRAMES: 2,
                qos.TAG_POINTS: 1,
                qos.MOTION: 1,
                qos.MODEL_STATE: 1,
                qos.REGISTERED_CLOUD: 2,
                qos.REGISTERED_STATE: 2,
            },
        )
        r = feed_corpus(ex, probe, nodes, valid, cases)
    finally:
        for n in (*nodes.values(), probe):
            ex.remove_node(n)
            n.destroy_node()
        ex.shutdown()
        ctx.try_shutdown()
    return {
        'cases': r.cases,
        'reported_as_expected': r.reported,
        'crashes': len(r.crashes),
        'nodes_down': r.nodes_down,
        'false_alarms': len(r.false_alarms),
        'phases_analysed': r.phases_analysed,
        'num_phases': r.num_phases,
        'seconds': r.seconds,
        'failures': r.failures[:10],
        'crash_messages': r.crashes[:10],
    }


def load(tmp: Path, size: int, num_phases: int) -> dict:
    from graphkit import run_load
    from mlv_ros.core.sim import simulate_study

    frames = list(simulate_study('normal', snr=20, size=size, num_phases=num_phases).frames)
    return run_load(frames, tmp).as_dict()


def slow_subscriber(tmp: Path) -> dict:
    """Frames beyond the recorder's queue depth published before its executor runs."""
    from mlv_msgs.msg import TaggedFrame
    from mlv_ros import conversions, qos
    from mlv_ros.core.sim.pattern import pattern_frames
    from mlv_ros.nodes.recorder import Recorder
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    rec = Recorder(
        context=ctx,
        parameter_overrides=[
            Parameter('output', value=str(tmp / 'slow.mcap')),
            Parameter('topics', value=[qos.FRAMES]),
        ],
    )
    src = rclpy.create_node('burst_source', context=ctx)
    pub = src.create_publisher(TaggedFrame, qos.FRAMES, qos.history_qos())
    msg = conversions.frame_to_msg(pattern_frames(num_phases=1, size=32)[0])
    try:
        for n in (rec, src):
            ex.add_node(n)
        spin_until(ex, lambda: pub.get_subscription_count() >= 1, 20)
        published = qos.STREAM_DEPTH * 3 // 2
        for _ in range(published):
            pub.publish(msg)
        stream = rec.streams[qos.FRAMES]
        spin_until(ex, lambda: stream.received + stream.lost >= published, 30)
        spin_until(ex, lambda: False, 0.3)  # let the last reports out
        rec.finish()
        return {
            'published': published,
            'recorded': rec.writer.topics[qos.FRAMES].count,
            'reported_lost': stream.lost + stream.missed,
            'silent_loss': published
            - rec.writer.topics[qos.FRAMES].count
            - stream.lost
            - stream.missed,
        }
    finally:
        for n in (rec, src):
            ex.remove_node(n)
            n.destroy_node()
        ex.shutdown()
        ctx.try_shutdown()


def _interrupted_recording(out: Path, min_bytes: int, sig: int) -> tuple[int, str]:
    """
    Record /mlv/frames in a recorder process and signal it mid-stream.

    A frame_source process streams the test pattern at a steady rate; ``sig`` goes to the recorder
    once ``out`` holds ``min_bytes`` (mid-stream). Returns the recorder's exit code and its log.
    """
    from mlv_ros import qos

    rec = subprocess.Popen(
        [
            _script('recorder'),
            '--ros-args',
            '-p',
            f'output:={out}',
            '-p',
            f"topics:=['{qos.FRAMES}']",
            '-p',
            'flush_period_s:=0.1',
            '-p',
            'chunk_size_kib:=64',
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    src = subprocess.Popen(
        [
            _script('frame_source'),
            '--ros-args',
            '-p',
            'source:=pattern',
            '-p',
            'num_phases:=200',
            '-p',
            'rate_factor:=0.1',
            '-p',
            'wait_for_subscribers:=1',
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and (not out.exists() or out.stat().st_size < min_bytes):
            if src.poll() is not None or rec.poll() is not None:
                break
            time.sleep(0.05)  # polling a file the other process writes: nothing to spin here
        rec.send_signal(sig)
        code = rec.wait(timeout=30)
    finally:
        for p in (rec, src):
            if p.poll() is None:
                p.kill()
            p.wait(timeout=10)
    return code, rec.stdout.read()


def sigterm(tmp: Path) -> dict:
    import re

    from mlv_ros import bagio, qos
    from rosbags.highlevel import AnyReader

    out = tmp / 'sigterm.mcap'
    code, log = _interrupted_recording(out, 500_000, signal.SIGTERM)
    m = re.search(r'recording closed .*messages=(\d+) received=(\d+) lost=(\d+)', log)
    recorded = bagio.bag_topics(out)[qos.FRAMES]['count']
    with AnyReader([out]) as reader:
        read_back = sum(1 for _ in reader.messages())
    return {
        'exit_code': code,
        'received': int(m.group(2)) if m else None,
        'recorded': recorded,
        'read_by_rosbags': read_back,
        'reported_lost': int(m.group(3)) if m else None,
        'equal': bool(m) and int(m.group(2)) == recorded == read_back,
    }


def sigkill(tmp: Path) -> dict:
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader
    from mlv_ros import bagio, qos

    out = tmp / 'sigkill.mcap'
    _interrupted_recording(out, 300_000, signal.SIGKILL)
    try:
        bagio.bag_topics(out)
        summary_readable = True
    except ValueError:
        summary_readable = False
    chunks = 0
    with open(out, 'rb') as fh:  # complete chunk records of the damaged file, read in order
        try:
            for record in StreamReader(fh, skip_magic=False, emit_chunks=True).records:
                chunks += isinstance(record, Chunk)
        except Exception:  # the record cut by the kill: where readable data ends
            pass
    result = bagio.recover(out, tmp / 'recovered.mcap')
    return {
        'file_bytes': out.stat().st_size,
        'summary_readable': summary_readable,
        'chunks_readable': chunks,
        'messages_recovered': result['topics'].get(qos.FRAMES, 0),
        'recovered_file_readable': bagio.bag_topics(tmp / 'recovered.mcap')[qos.FRAMES]['count']
        == result['topics'].get(qos.FRAMES, 0),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description='reliability benchmark (JSON on stdout)')
    parser.add_argument('--quick', action='store_true', help='smaller studies')
    parser.add_argument(
        '--repeat', type=int, default=1, help='repeats of the load / signal sections'
    )
    args = parser.parse_args(argv)
    out = {'ros_domain_id': int(os.environ['ROS_DOMAIN_ID'])}
    with tempfile.TemporaryDirectory(prefix='mlv_reliability_') as d:
        tmp = Path(d)
        out['dicom_corpus'] = dicom_corpus(tmp)
        out['message_corpus'] = message_corpus(num_phases=4)
        runs = {'load': [], 'slow_subscriber': [], 'sigterm': [], 'sigkill': []}
        for i in range(args.repeat):
            run_dir = tmp / f'run{i}'
            run_dir.mkdir()
            runs['load'].append(
                load(run_dir, 128 if args.quick else 256, 10 if args.quick else 25)
            )
            runs['slow_subscriber'].append(slow_subscriber(run_dir))
            runs['sigterm'].append(sigterm(run_dir))
            runs['sigkill'].append(sigkill(run_dir))
        out.update({k: v[0] if len(v) == 1 else v for k, v in runs.items()})
    mc, dc = out['message_corpus'], out['dicom_corpus']
    out['totals'] = {
        'cases_tried': dc['cases'] + mc['cases'],
        'cases_reported_as_expected': dc.get('as_expected', 0) + mc['reported_as_expected'],
        'crashes': dc['crashes'] + mc['crashes'],
        'nodes_down': len(mc['nodes_down']),
        'frames_lost': sum(r['frames_lost'] for r in runs['load']),
        'silent_losses': sum(r['silent_loss'] for r in runs['slow_subscriber']),
        'sigterm_received_equals_recorded': all(r['equal'] for r in runs['sigterm']),
        'sigkill_messages_recovered': [r['messages_recovered'] for r in runs['sigkill']],
    }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
