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
The nodes' stream policy without ROS (mlv_ros.core.streaming).

What the solver releases for which arrival order, the tag detector's per-slice phase order with
skipped phases, and the pairing of clouds with model states by stamp, with bounded memory.
"""

import itertools

from mlv_ros.core.streaming import InOrderBuffer, PhaseSchedule, Slot, StampPairer
from mlv_ros.core.types import TagPointSet
import pytest

SLICES = [(0, 0), (0, 1), (1, 0)]  # (view, slice): 2 SA + 1 LA


def tag_set(view, slice_index, phase, num_phases=4):
    """Return an empty tag point set of a 2 SA + 1 LA study (what the schedule reads of it)."""
    return TagPointSet(
        view=view,
        slice_index=slice_index,
        phase_index=phase,
        num_phases=num_phases,
        geometry=None,
        num_sa_slices=2,
        num_la_slices=1,
    )


def solve_all(schedule, force=False):
    """Release every phase that is ready, in order, as the solver node does; return them."""
    out = []
    while (r := schedule.ready(force)) is not None:
        force = False
        out.append((r.phase, sorted(r.sets), r.complete))
        schedule.done(r.phase)
    return out


@pytest.mark.parametrize('order', ['slice_major', 'phase_major'])
def test_every_phase_solved_once_in_order_whatever_the_arrival_order(order):
    sets = [(s, p) for s in SLICES for p in range(4)]
    if order == 'phase_major':
        sets.sort(key=lambda sp: sp[1])
    schedule, solved = PhaseSchedule(), []
    for (view, idx), phase in sets:
        assert schedule.add(tag_set(view, idx, phase)) == PhaseSchedule.NEW
        solved += solve_all(schedule)
    assert solved == [(p, SLICES, True) for p in range(4)]
    assert schedule.finished and not schedule.assembler.phases


def test_an_incomplete_phase_waits_until_a_later_one_is_complete():
    schedule = PhaseSchedule()
    for key in SLICES[:2]:  # phase 0 without the LA slice
        schedule.add(tag_set(*key, 0))
    assert solve_all(schedule) == [] and schedule.waiting()
    for key in SLICES[:2]:
        schedule.add(tag_set(*key, 1))
    assert solve_all(schedule) == []  # phase 1 is not complete either
    schedule.add(tag_set(*SLICES[2], 1))
    assert solve_all(schedule) == [(0, SLICES[:2], False), (1, SLICES, True)]


def test_forcing_releases_one_incomplete_phase_only():
    schedule = PhaseSchedule()
    for phase in (0, 1):
        schedule.add(tag_set(*SLICES[0], phase))
    assert solve_all(schedule) == []
    assert solve_all(schedule, force=True) == [(0, SLICES[:1], False)]
    assert schedule.next_phase == 1 and schedule.waiting() and not schedule.finished


def test_stale_and_duplicate_sets():
    schedule = PhaseSchedule()
    for key in SLICES:
        schedule.add(tag_set(*key, 0))
    assert solve_all(schedule) == [(0, SLICES, True)]
    assert schedule.add(tag_set(*SLICES[0], 0)) == PhaseSchedule.STALE
    assert schedule.add(tag_set(*SLICES[0], 2)) == PhaseSchedule.NEW
    assert schedule.add(tag_set(*SLICES[0], 2)) == PhaseSchedule.DUPLICATE
    assert schedule.assembler.duplicates == 1


def test_nothing_is_released_before_the_study_size_is_known():
    schedule = PhaseSchedule()
    assert schedule.ready(force=True) is None and not schedule.finished


def test_in_order_buffer_reorders_each_slice():
    buf = InOrderBuffer(max_pending=3)
    out = []
    for phase, key in [(2, 'a'), (0, 'b'), (1, 'a'), (0, 'a'), (1, 'b')]:
        assert buf.offer(key, phase, f'{key}{phase}')
        out += [(key, s) for s in buf.drain(key)]
    assert out == [
        ('b', Slot(0, 'b0')),
        ('a', Slot(0, 'a0')),
        ('a', Slot(1, 'a1')),
        ('a', Slot(2, 'a2')),
        ('b', Slot(1, 'b1')),
    ]


@pytest.mark.parametrize('max_pending', [1, 2, 3])
def test_a_missing_phase_is_skipped_once_max_pending_later_ones_wait(max_pending):
    buf = InOrderBuffer(max_pending=max_pending)
    released = []
    for phase in range(1, 6):  # phase 0 never comes
        buf.offer('s', phase, phase)
        released += list(buf.drain('s'))
        if phase < max_pending:
            assert released == []
    assert released == [Slot(0, None)] + [Slot(p, p) for p in range(1, 6)]
    assert not buf.offer('s', 0, 'late')  # its slot was given up


def test_duplicates_and_stand_ins():
    buf = InOrderBuffer(max_pending=3)
    assert buf.offer('s', 1, 'x') and not buf.offer('s', 1, 'y')  # held already
    assert buf.expects('s', 0) and not buf.expects('s', 1) and not buf.expects('s', 2)
    buf.fill('s', 0)  # a stand-in went out for phase 0
    assert list(buf.drain('s')) == [Slot(1, 'x')]
    assert not buf.offer('s', 0, 'z') and buf.expects('s', 2)
    with pytest.raises(ValueError, match='max_pending'):
        InOrderBuffer(0)


def test_pairs_come_out_by_stamp_in_cloud_order():
    pairer = StampPairer(max_unpaired=10)
    for key in (3, 1, 2):
        pairer.add('cloud', key, f'c{key}')
    for key in (2, 3):
        pairer.add('state', key, f's{key}')
    assert pairer.pairs() == [(3, 'c3', 's3'), (2, 'c2', 's2')]
    assert pairer.pairs() == [] and list(pairer.held['cloud']) == [1]
    assert pairer.discard(1) == {'cloud': 'c1'} and pairer.discard(1) == {}


def test_unpaired_items_are_bounded_oldest_first():
    pairer = StampPairer(max_unpaired=3)
    dropped = []
    for key in itertools.count():
        if key == 6:
            break
        pairer.add('state', key, key)
        dropped += pairer.trim('state')
    assert dropped == [0, 1, 2] and list(pairer.held['state']) == [3, 4, 5]
    assert pairer.trim('cloud') == []
    with pytest.raises(ValueError, match='max_unpaired'):
        StampPairer(0)
