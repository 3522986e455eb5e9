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
``mlv-ros simulate``: write a simulated tagged-MRI study (DICOM + ground truth).

``--random SEED`` draws an acquisition protocol (:mod:`mlv_ros.core.sim.protocol`), ``--protocol
FILE`` fixes any of its items (alone: the items it lacks take the preset's values); either way
``OUT/protocol.yaml`` records every item.
"""

from __future__ import annotations

from pathlib import Path
import sys

from mlv_ros.cli import describe_os_error, number, one_line


def add_arguments(parser):
    parser.add_argument(
        '--preset',
        default=None,
        help='normal | hypertrophic | dilated | infarct | cylinder, or a preset YAML '
        'path (default normal); with --random/--protocol it fixes the shape',
    )
    parser.add_argument(
        '--out',
        required=True,
        type=Path,
        help='output directory (DICOM under OUT/dicom, ground truth in OUT)',
    )
    parser.add_argument(
        '--random',
        type=number(int, 0),
        default=None,
        metavar='SEED',
        help='draw every acquisition item from its documented range (README, '
        "'Random protocols'); writes OUT/protocol.yaml",
    )
    parser.add_argument(
        '--tag-lines',
        choices=('grid', 'any'),
        default='grid',
        help='with --random: grid (default; the grid study the seed always drew) or any (tag '
        'lines drawn too: grid, a single-line pair or one family, from a stream of their own)',
    )
    parser.add_argument(
        '--protocol',
        type=Path,
        default=None,
        metavar='FILE',
        help='protocol YAML fixing any items (with --random the rest are drawn, '
        "alone they take the preset's values)",
    )
    parser.add_argument(
        '--snr',
        type=number(float, 0.0),
        default=None,
        help="myocardium / noise sigma (default: the preset's, 20); 0 = noiseless",
    )
    parser.add_argument(
        '--size', type=number(int, 16), default=None, help='rows = columns (default 256)'
    )
    parser.add_argument(
        '--phases', type=number(int, 2), default=None, help='phases per cycle (default 25)'
    )
    parser.add_argument(
        '--subplanes',
        type=number(int, 1),
        default=None,
        help='through-slice sub-planes (default 5)',
    )
    parser.add_argument(
        '--seed',
        type=number(int, 0),
        default=None,
        help='noise, UID and file-name seed (default: the --random SEED, else 0)',
    )
    parser.add_argument(
        '--points',
        type=number(int, 0),
        default=2000,
        help='material points with stored trajectories',
    )
    parser.add_argument('--no-progress', action='store_true', help='hide the progress bar')


def _fail(msg) -> int:
    print(f'mlv-ros simulate: {one_line(msg)}', file=sys.stderr)
    return 2


def _protocol(args):
    """Return (protocol, preset) from --random/--protocol and the overrides; raise ValueError."""
    from mlv_ros.core.sim.protocol import (
        check_items,
        complete_protocol,
        draw_protocol,
        load_protocol,
        protocol_preset,
        SHAPES,
    )

    fixed = load_protocol(args.protocol) if args.protocol else {}
    if args.preset is not None:
        if args.preset not in SHAPES:
            raise ValueError(
                f'with --random/--protocol, --preset names the shape: one of '
                f'{", ".join(SHAPES)} (got {args.preset!r})'
            )
        fixed['shape'] = args.preset
    if args.size is not None:
        fixed['size'] = args.size
    if args.phases is not None:
        fixed['num_phases'] = args.phases
    if args.snr is not None:
        fixed['snr'] = None if args.snr == 0 else args.snr
    fixed = check_items(fixed)
    protocol = (
        draw_protocol(args.random, fixed, tag_lines=args.tag_lines)
        if args.random is not None
        else complete_protocol(fixed)
    )
    return protocol, protocol_preset(protocol)


def run(args) -> int:
    from mlv_ros.core.io import write_groundtruth, write_study_dicom
    from mlv_ros.core.sim import load_preset
    from tqdm import tqdm

    randomised = args.random is not None or args.protocol is not None
    seed = args.seed if args.seed is not None else (args.random if args.random is not None else 0)
    protocol = None
    if args.tag_lines != 'grid' and args.random is None:
        return _fail(f'--tag-lines {args.tag_lines} draws tag lines: give --random SEED too')
    try:
        if randomised:
            protocol, preset = _protocol(args)
        else:
            preset = load_preset(args.preset or 'normal')
    except (FileNotFoundError, ValueError) as exc:
        return _fail(exc)
    try:  # before the simulation: an --out that cannot be written fails now, not minutes later
        Path(args.out).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return _fail(f'cannot write --out: {describe_os_error(exc)}')
    if protocol is not None:
        snr = protocol['snr']
    else:
        snr = preset['imaging']['snr'] if args.snr is None else args.snr
        snr = None if snr == 0 else snr
    try:
        study = _simulate(args, preset, protocol, snr, seed)
    except ValueError as exc:
        return _fail(exc)
    out = Path(args.out)
    extra, options = None, {}
    if protocol is not None:
        from mlv_ros.core.sim.protocol import dicom_options, save_protocol

        options = dicom_options(protocol, study, names_seed=seed)
        extra = {'protocol': protocol, 'dicom': options}
    series = [(study, out / 'dicom', options)]
    if protocol is not None and protocol['tag_lines'] == 'pair':
        try:
            series = _line_pair(args, preset, study, options, protocol)
        except ValueError as exc:
            return _fail(exc)
    total = sum(len(s[0].frames) for s in series)
    wbar = tqdm(total=total, unit='file', desc='write DICOM', disable=args.no_progress)
    try:
        files = []
        for st, where, opts in series:
            done0 = len(files)
            files += write_study_dicom(
                st,
                where,
                progress=lambda done, total, d0=done0: wbar.update(d0 + done - wbar.n),
                **opts,
            )
        jpath, npath = write_groundtruth(study, out, n_points=args.points, extra=extra)
    except OSError as exc:  # e.g. the disk filled up while writing
        wbar.close()
        return _fail(f'writing the study failed: {describe_os_error(exc)}')
    finally:
        wbar.close()
    msg = (
        f'wrote {len(files)} DICOM files to {out / "dicom"}; ground truth {jpath.name}, '
        f'{npath.name}'
    )
    if protocol is not None:
        save_protocol(protocol, out / 'protocol.yaml', header=_protocol_header(args, seed))
        msg += ', protocol.yaml'
    print(msg)
    return 0


def _simulate(args, preset: dict, protocol: dict | None, snr, seed: int):
    """
    Simulate the study behind a progress bar (closed however it ends).

    Parameters
    ----------
    args : argparse.Namespace
        The command line (``size``, ``phases``, ``subplanes``, ``no_progress``).
    preset : dict
        The phantom preset.
    protocol : dict or None
        A drawn protocol: its size and phases are protocol items, the command line's are not used.
    snr : float or None
        Noise level (None: noiseless).
    seed : int
        Noise seed.

    Returns
    -------
    mlv_ros.core.sim.Study

    """
    from mlv_ros.core.sim import simulate_study
    from tqdm import tqdm

    bar = tqdm(total=1, unit='img', desc=f'simulate {preset["name"]}', disable=args.no_progress)

    def progress(done, total):
        bar.total = total
        bar.update(done - bar.n)

    try:
        if protocol is not None:  # size and phases are protocol items
            return simulate_study(
                preset, snr=snr, seed=seed, subplanes=args.subplanes, progress=progress
            )
        return simulate_study(
            preset,
            snr=snr,
            size=args.size,
            num_phases=args.phases,
            seed=seed,
            subplanes=args.subplanes,
            progress=progress,
        )
    finally:
        bar.close()


def _line_pair(args, preset: dict, study, options: dict, protocol: dict) -> list:
    """
    Simulate the second single-line series of every slice (``tag_lines: pair``).

    Its lines turned by ``line_pair_angle_deg``, the heart shifted by ``line_pair_shift_mm`` and
    ``line_pair_through_mm`` (another breath-hold). Returns ``[(study, folder, write options)]``
    for both: ``OUT/dicom/lines_1`` and ``OUT/dicom/lines_2`` (the second numbered after the
    first, its own file names).
    """
    from mlv_ros.core.sim.study import line_pair_study

    second = line_pair_study(
        preset,
        study,
        protocol['line_pair_angle_deg'],
        shift_mm=protocol['line_pair_shift_mm'],
        through_mm=protocol['line_pair_through_mm'],
        subplanes=args.subplanes,
    )
    out = Path(args.out) / 'dicom'
    later = {
        **options,
        'series_offset': len(study.series_uids) + 1,
        'names_seed': int(options.get('names_seed', 0)) + 1,
    }
    return [(study, out / 'lines_1', options), (second, out / 'lines_2', later)]


def _protocol_header(args, seed: int) -> str:
    """Say in protocol.yaml where the protocol came from and how to simulate it again."""
    how = f'--random {args.random}' if args.random is not None else f'--protocol {args.protocol}'
    if args.random is not None and args.tag_lines != 'grid':
        how += f' --tag-lines {args.tag_lines}'
    sub = f' --subplanes {args.subplanes}' if args.subplanes is not None else ''
    return (
        f'Acquisition protocol of this study (mlv-ros simulate {how}; noise seed '
        f'{seed}).\n'
        f'Reproduce: mlv-ros simulate --protocol protocol.yaml --seed {seed}{sub} '
        '--out DIR\n'
        f"Items and ranges: README.md, 'Random protocols'."
    )
