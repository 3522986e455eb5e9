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
The console of ``mlv-ros run`` / ``demo`` (mlv_ros.console): progress bar and summary.

The console of ``mlv-ros run`` / ``demo`` (mlv_ros.console): a progress bar over phases
only on a terminal and not with --no-progress, and a short summary (at most 30 lines whatever the
run) that says what was run, how it ended, the accuracy, volumes, the verdicts with the
degraded and failed phases grouped by reason, where the results are and the exit status.
"""

import io

from mlv_ros.console import (
    MAX_SUMMARY_LINES,
    phase_ranges,
    reason_groups,
    RunConsole,
    summary_lines,
)


class Terminal(io.StringIO):
    def isatty(self):
        return True


def run_summary(num_phases=25, degraded=None, failed=None, **extra):
    degraded, failed = degraded or {}, failed or {}
    ok = [p for p in range(num_phases) if str(p) not in degraded and str(p) not in failed]
    return {
        'source': {'source': 'phantom', 'preset': 'normal'},
        'study_id': 'phantom-abc',
        'seconds': 61.2,
        'frames_published': 11 * num_phases,
        'phases_solved': num_phases,
        'metrics_published': num_phases,
        'num_phases': num_phases,
        'complete': True,
        'interrupted': None,
        'failed': None,
        'phases_complete': True,
        'phases_ok': ok,
        'phases_degraded': degraded,
        'phases_failed': failed,
        'registration_verdict': {'verdict': 'ok', 'reasons': ''},
        'run_dir': 'runs/x',
        'mcap': 'runs/x/run.mcap',
        'cavity_volume_ml': {str(p): 120.0 - 50.0 * min(p, 8) / 8 for p in range(num_phases)},
        **extra,
    }


def test_bar_only_on_a_terminal_and_not_with_no_progress():
    term = Terminal()
    console = RunConsole(progress=True, stream=term)
    for done in range(0, 5):
        console.phase(done, 4)
    console.close()
    assert 'phases analysed' in term.getvalue() and '4/4' in term.getvalue()
    for console in (
        RunConsole(progress=True, stream=io.StringIO()),
        RunConsole(progress=False, stream=Terminal()),
    ):
        console.phase(1, 4)
        console.line('[mlv-ros] phase 1/4 analysed')
        console.close()
        assert console.stream.getvalue() == ''
    quiet = RunConsole(progress=False, stream=io.StringIO())
    quiet.line(
        '[mlv-ros] live view: ws://127.0.0.1:8765 (Foxglove: ...)'
    )  # needed while the run goes on
    assert quiet.stream.getvalue().startswith('[mlv-ros] live view: ws://')
    verbose = RunConsole(verbose=True, progress=False, stream=io.StringIO())
    verbose.line('[mlv-ros] phase 1/4 analysed')
    assert verbose.stream.getvalue() == '[mlv-ros] phase 1/4 analysed\n'


def test_summary_of_a_good_run_says_what_a_user_needs():
    acc = {
        'es': {'phase': 8, 'median_mm': 0.384, 'p95_mm': 1.18, 'twist_error_deg': 0.65},
        'per_phase': [{'phase': p, 'median_mm': 0.1 * p} for p in range(25)],
        'coverage': 0.97,
    }
    lines = summary_lines(
        run_summary(),
        exit_status=0,
        exit_reason='complete',
        accuracy=acc,
        report='runs/x/report/index.html',
    )
    text = '\n'.join(lines)
    assert len(lines) <= 12, text
    for words in (
        'phantom normal',
        'complete after 61.2 s: 25 of 25 phases solved',
        'median 0.38 mm, p95 1.18 mm',
        'twist 0.65°',
        'worst phase: 24',
        'ED 120.0 ml, ES 70.0 ml (phase 8), ejection fraction 42 %',
        '25 ok, 0 degraded, 0 failed',
        'runs/x/run.mcap',
        'report runs/x/report/index.html',
        'exit 0: complete',
    ):
        assert words in text, (words, text)


def test_summary_of_a_bad_run_stays_short_and_groups_the_reasons():
    """
    Check that the summary of 200 mostly flagged phases keeps to 30 lines.

    200 phases, most flagged for a mix of reasons with different numbers in each: the summary
    keeps to 30 lines, counts every phase, and names the phases of each kind of reason.
    """
    n = 200
    failed = {
        str(p): f'{p % 7} of 160 ED tag points tracked ({p % 7 / 1.6:.0f}% < 10%)'
        for p in range(100, 200)
    }
    degraded = {
        str(p): (
            f'{p % 5} of 8 SA slices with 3+ tag points (12% < 60%)'
            if p % 2
            else f'fit residual {p / 100:.2f} mm = 0.{p} px (> 0.5 px)'
        )
        + '; a reason of its own: '
        + ''.join(chr(97 + int(d)) for d in str(p))
        for p in range(1, 100)
    }
    failed['150'] += "; ejection fraction 0.99 outside [-0.3, 0.95]: not a ventricle's volume"
    summary = run_summary(
        n,
        degraded,
        failed,
        complete=False,
        registration_verdict={
            'verdict': 'degraded',
            'reasons': 'ED wall thickness 35.0 mm on average',
        },
        messages_of_other_studies={'tag_detector': 12},
    )
    lines = summary_lines(summary, exit_status=3, exit_reason='the study could not be tracked')
    text = '\n'.join(lines)
    assert len(lines) <= MAX_SUMMARY_LINES, text
    assert 'verdicts: 1 ok, 99 degraded, 100 failed' in text
    assert 'failed 100-199: 2 of 160 ED tag points tracked' in text, (
        text
    )  # one group, its first wording
    assert 'degraded 1, 3, 5, 7, 9, 11, 13, 15, ... (50 phases): 1 of 8 SA slices' in text, text
    assert 'failed 150: ejection fraction 0.99' in text
    assert (
        'more reason(s) for degraded phases' in text
    )  # 99 phases with a reason of their own each
    assert 'registration: degraded: ED wall thickness 35.0 mm' in text
    assert '12 message(s) of another study or run ignored, 0 /diagnostics' in text
    assert lines[-1] == 'exit 3: the study could not be tracked'
    assert all(len(line) <= 220 for line in lines)


def test_reason_groups_and_phase_ranges():
    groups = reason_groups({'3': 'a 1 b', '4': 'a 2 b; c', '5': 'a 9 b', '9': 'c'})
    assert groups == [([3, 4, 5], 'a 1 b'), ([4, 9], 'c')]
    assert phase_ranges([9, 3, 4, 5, 7, 8, 12, 13]) == '3-5, 7-9, 12, 13'
    assert phase_ranges([1, 2]) == '1, 2' and phase_ranges([]) == ''


def test_summary_of_a_run_that_failed_before_any_phase():
    summary = run_summary(
        8, complete=False, phases_solved=0, metrics_published=0, cavity_volume_ml={}
    )
    summary.update(failed='registration: registration failed (reason: ...)', phases_ok=[])
    lines = summary_lines(summary, exit_status=1, exit_reason='not complete')
    text = '\n'.join(lines)
    assert (
        'result: failed after 61.2 s: 0 of 8 phases solved' in text
        and 'failure: registration: ' in text
    )
    assert 'verdicts: no phase analysed' in text and 'volumes' not in text, text
