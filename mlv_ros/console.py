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
The console of ``mlv-ros run`` and ``mlv-ros demo``.

One progress bar over phases while the graph runs, then a short summary of the run.

By default a run shows:

- a progress bar over the phases analysed, on stderr, only when stderr is a terminal and
  ``--no-progress`` (or ``--quiet``) was not given, so logs and pipes never hold bar redraws;
- the nodes' WARN and ERROR lines (what a user must act on), not their INFO lines;
- at the end, a summary of at most :data:`MAX_SUMMARY_LINES` lines on stdout
  (:func:`summary_lines`): what was run, how it ended, accuracy against the ground truth when
  there is one, ED / ES volumes and the ejection fraction, the verdict counts with the degraded
  and failed phases grouped by reason, the registration's verdict, where the results are, and
  the exit status with its reason.

``--verbose`` adds everything else: the nodes' INFO lines, one line per event of the run (each
phase analysed, the study chosen, an interruption), and the whole summary as JSON (stdout,
before the short summary). Every number is in ``RUN_DIR/summary.json`` either way.
"""

from __future__ import annotations

import re
import sys

#: The short summary never has more lines than this.
MAX_SUMMARY_LINES = 30
#: Reason groups shown per verdict level (the rest are counted; summary.json has them all).
MAX_REASON_GROUPS = 4
#: Event lines shown without --verbose too: what the user needs while the run goes on.
ALWAYS_SHOWN = ('[mlv-ros] live view:',)
_NUMBER = re.compile(r'[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?')


class RunConsole:
    """
    What a run prints while it runs: the progress bar and the run's event lines.

    The progress bar (:meth:`phase`) and, with ``verbose``, the run's event lines (:meth:`line`).

    Parameters
    ----------
    verbose : bool
        Print every event line and the nodes' INFO lines.
    progress : bool
        Show the bar (still only when ``stream`` is a terminal).
    stream : file, optional
        Where both go (default ``sys.stderr``).

    """

    def __init__(self, verbose: bool = False, progress: bool = True, stream=None):
        self.stream = stream or sys.stderr
        self.verbose = bool(verbose)
        self.show_bar = bool(progress) and _isatty(self.stream)
        self.bar = None

    def quiet_nodes(self):
        """
        Keep the nodes' INFO lines off the console unless verbose.

        WARN and ERROR stay (what a user must act on). Returns what puts the level back (the
        process may run more after).

        The threshold is the default level of every ROS logger in this process, which also
        decides what reaches /rosout: INFO statuses are still on /diagnostics and in the
        recording.
        """
        if self.verbose:
            return lambda: None
        from rclpy.logging import get_logger_effective_level, LoggingSeverity, set_logger_level

        before = get_logger_effective_level('')
        set_logger_level('', LoggingSeverity.WARN)
        return lambda: set_logger_level('', before)

    def line(self, text: str) -> None:
        """
        Show an event of the run (``run_graph``'s ``progress``) if it is to be shown.

        Shown with ``verbose`` only, but for the few of :data:`ALWAYS_SHOWN` (e.g. the live view's
        address).
        """
        if not self.verbose and not text.startswith(ALWAYS_SHOWN):
            return
        if self.bar is not None:
            self.bar.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)

    def phase(self, done: int, total: int) -> None:
        """``done`` of ``total`` phases analysed (``run_graph``'s ``on_phase``)."""
        if not self.show_bar or total <= 0:
            return
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(
                total=total,
                unit='phase',
                desc='phases analysed',
                file=self.stream,
                leave=False,
                dynamic_ncols=True,
                mininterval=0,
            )  # phases are seconds apart: draw each
        self.bar.total = total
        self.bar.update(max(0, min(done, total) - self.bar.n))

    def close(self) -> None:
        """Take the bar off the screen (before the summary is printed)."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def phase_ranges(phases, max_items: int = 8) -> str:
    """
    ``[3, 4, 5, 9]`` → ``'3-5, 9'``; past ``max_items`` runs, the rest are counted (``'1, 3, 5, ...

    (50 phases)'``).
    """
    items, run = [], []
    ordered = sorted({int(p) for p in phases})
    for p in ordered + [None]:
        if p is not None and run and p == run[-1] + 1:
            run.append(p)
            continue
        if run:
            items += [f'{run[0]}-{run[-1]}'] if len(run) > 2 else [str(r) for r in run]
        run = [p]
    if len(items) > max_items:
        return ', '.join(items[:max_items]) + f', ... ({len(ordered)} phases)'
    return ', '.join(items)


def reason_groups(phases: dict) -> list[tuple[list[int], str]]:
    """
    Phases → reasons (``"reason; reason"``, as in summary.json) grouped by kind of reason.

    Reasons that differ only in their numbers are one kind (``12 of 160 ED tag points tracked
    (8% < 10%)`` and ``3 of 160 ...``); each group is shown with the first phase's wording.
    Largest groups first.
    """
    groups: dict[str, tuple[list[int], str]] = {}
    for phase, text in sorted(phases.items(), key=lambda kv: int(kv[0])):
        for reason in [r for r in str(text).split('; ') if r] or ['no reason given']:
            kind = _NUMBER.sub('#', reason)
            members, first = groups.setdefault(kind, ([], reason))
            if int(phase) not in members:
                members.append(int(phase))
    return sorted(groups.values(), key=lambda g: (-len(g[0]), g[0][0]))


def _clip(text: str, width: int = 160) -> str:
    text = ' '.join(str(text).split())
    return text if len(text) <= width else text[:width - 1] + '…'


def source_text(source: dict) -> str:
    kind = source.get('source')
    if kind == 'phantom':
        extra = ', '.join(
            f'{k} {source[k]:g}' for k in ('size', 'num_phases', 'snr') if k in source
        )
        return f'phantom {source.get("preset")}' + (f' ({extra})' if extra else '')
    if kind in ('dicom', 'bag'):
        return f'{kind} {source.get("path")}' + (
            f' (study {source["study"]})' if source.get('study') else ''
        )
    return str(kind)


def volumes_text(volumes: dict, failed=()) -> str | None:
    """
    Return ED / ES cavity volume and the ejection fraction as text.

    From phase → volume (ml), leaving out failed phases (ES: the smallest volume).
    """
    kept = {
        int(p): float(v)
        for p, v in (volumes or {}).items()
        if str(p) not in {str(f) for f in failed}
    }
    if 0 not in kept or len(kept) < 2:
        return None
    edv = kept[0]
    es, esv = min(kept.items(), key=lambda kv: kv[1])
    ef = (edv - esv) / edv if edv > 0 else float('nan')
    return (
        f'volumes: ED {edv:.1f} ml, ES {esv:.1f} ml (phase {es}), ejection fraction '
        f'{100 * ef:.0f} %'
    )


def accuracy_text(accuracy: dict | None) -> list[str]:
    """Return the accuracy against the ground truth, in at most two lines."""
    if not accuracy:
        return []
    if accuracy.get('error'):
        return [f'accuracy: not evaluated ({accuracy["error"]})']
    es = accuracy.get('es') or {}
    lines = []
    if es:
        twist = es.get('twist_error_deg')
        lines.append(
            f'accuracy at end-systole (phase {es.get("phase", accuracy.get("es_phase"))}): median '
            f'{es["median_mm"]:.2f} mm, p95 {es["p95_mm"]:.2f} mm'
            + (f', twist {twist:.2f}°' if twist is not None else '')
            + ' (3D error against the truth)'
        )
    per_phase = accuracy.get('per_phase') or []
    if per_phase:
        worst = max(per_phase, key=lambda r: r.get('median_mm', 0.0))
        lines.append(
            f'worst phase: {worst.get("phase")}, median {worst["median_mm"]:.2f} mm'
            + (
                f'; myocardium covered {100 * accuracy["coverage"]:.0f} %'
                if accuracy.get('coverage')
                else ''
            )
        )
    return lines


def verdict_lines(summary: dict) -> list[str]:
    """Verdict counts, then the degraded and failed phases grouped by reason (a few lines)."""
    ok = summary.get('phases_ok') or []
    degraded, failed = summary.get('phases_degraded') or {}, summary.get('phases_failed') or {}
    if not (ok or degraded or failed):
        lines = ['verdicts: no phase analysed']
    else:
        lines = [
            f'verdicts: {len(ok)} ok, {len(degraded)} degraded, {len(failed)} failed'
            + ('' if degraded or failed else ' (every phase analysed is ok)')
        ]
    for name, phases in (('failed', failed), ('degraded', degraded)):
        groups = reason_groups(phases)
        for members, reason in groups[:MAX_REASON_GROUPS]:
            lines.append(f'  {name} {phase_ranges(members)}: {_clip(reason, 130)}')
        if len(groups) > MAX_REASON_GROUPS:
            lines.append(
                f'  ... {len(groups) - MAX_REASON_GROUPS} more reason(s) for {name} phases: '
                f'phases_{name} in summary.json'
            )
    reg = summary.get('registration_verdict')
    if reg and reg.get('verdict') not in (None, 'ok'):
        lines.append(f'registration: {reg["verdict"]}: {_clip(reg.get("reasons"), 140)}')
    return lines


def summary_lines(
    summary: dict,
    *,
    exit_status: int,
    exit_reason: str | None,
    accuracy: dict | None = None,
    report: str | None = None,
    volumes: dict | None = None,
) -> list[str]:
    """
    Return the run's short summary: at most :data:`MAX_SUMMARY_LINES` lines.

    Parameters
    ----------
    summary : dict
        ``run_graph``'s summary (as in ``summary.json``).
    exit_status : int
        What the command exits with.
    exit_reason : str, optional
        Why, when not 0 (one line).
    accuracy : dict, optional
        ``evaluate_run``'s result against the ground truth (phantom or simulated study).
    report : str, optional
        The report's index file, when one was built.
    volumes : dict, optional
        Phase → cavity volume, ml (default ``summary["cavity_volume_ml"]``).

    """
    n, solved, analysed = (
        summary.get('num_phases', 0),
        summary.get('phases_solved', 0),
        summary.get('metrics_published', 0),
    )
    if summary.get('interrupted'):
        how = f'interrupted by {summary["interrupted"]}'
    elif summary.get('failed'):
        how = 'failed'
    else:
        how = 'complete' if summary.get('complete') else 'incomplete'
    lines = [
        f'run: {source_text(summary.get("source") or {})}, study {summary.get("study_id") or "?"}'
        + (f' (run {summary["run_id"]})' if summary.get('run_id') else ''),
        f'result: {how} after {summary.get("seconds", 0):.1f} s: {solved} of {n} phases '
        f'solved, {analysed} analysed, '
        f'{summary.get("frames_published", 0)} frames',
    ]
    if summary.get('failed'):
        lines.append(f'failure: {_clip(summary["failed"], 200)}')
    lines += accuracy_text(accuracy)
    vol = volumes_text(
        volumes if volumes is not None else summary.get('cavity_volume_ml') or {},
        failed=(summary.get('phases_failed') or {}).keys(),
    )
    if vol:
        lines.append(vol)
    lines += verdict_lines(summary)
    lines += _side_notes(summary)
    run_dir = summary.get('run_dir', '')
    where = (
        f'{run_dir}/summary.json'
        if not summary.get('summary_error')
        else 'no summary.json '
        f'({summary["summary_error"].removeprefix("summary.json not written: ")})'
    )
    lines.append(
        f'results: {summary.get("mcap")} and {where}' + (f'; report {report}' if report else '')
    )
    lines.append(
        f'exit {exit_status}' + (f': {_clip(exit_reason, 200)}' if exit_reason else ': complete')
    )
    if len(lines) > MAX_SUMMARY_LINES:  # keep the head and the exit line
        lines = lines[:MAX_SUMMARY_LINES - 2] + ['... (see summary.json)', lines[-1]]
    return lines


def _side_notes(summary: dict) -> list[str]:
    """Return the summary's lines on what the run left out, ignored, showed or failed to record."""
    out = []
    if summary.get('left_out'):
        out.append(
            f'input: {len(summary["left_out"])} part(s) of the study left out (left_out in '
            'summary.json)'
        )
    other = sum((summary.get('messages_of_other_studies') or {}).values())
    statuses = summary.get('statuses_of_other_graphs') or 0
    if other or statuses:
        out.append(
            f'isolation: {other} message(s) of another study or run ignored, {statuses} '
            '/diagnostics '
            'status(es) of other graphs left out of the recording'
        )
    view = summary.get('live_view')
    if view:
        out.append(f'live view: {view.get("url")}, {view.get("phases_shown", 0)} phase(s) shown')
    if summary.get('recording_error'):
        out.append(f'recording: stopped early: {_clip(summary["recording_error"], 150)}')
    return out
