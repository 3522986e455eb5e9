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
Stream policy of the graph's nodes, without ROS: what is ready, in what order, paired with what.

Three rules the nodes apply to messages arriving in any order, kept here (pure Python) so they
can be tested without a running graph:

- :class:`PhaseSchedule` (the solver): tag point sets gathered per phase; phase t is released
  once every slice's set for t is in, once a later phase is complete (a slice that never comes
  must not hold the study up), or when the caller forces it (its input has been quiet for long).
- :class:`InOrderBuffer` (the tag detector): each slice's frames taken in phase order; a missing
  phase is skipped once ``max_pending`` later ones wait for it.
- :class:`StampPairer` (the analyzer, the live view): a point cloud and the model state of the
  same header stamp paired, with bounded memory for those whose pair never comes.
"""

from __future__ import annotations

from typing import Hashable, Iterator, NamedTuple

from mlv_ros.core.types import TagPointSet


class Release(NamedTuple):
    """
    A phase the solver may solve now.

    Attributes
    ----------
    phase : int
        The phase index.
    sets : dict
        ``{(view, slice): TagPointSet}`` of the sets in (all slices, or fewer).
    complete : bool
        Whether every expected slice's set is in (False: solved without the missing ones).

    """

    phase: int
    sets: dict
    complete: bool


class PhaseSchedule:
    """
    Which phase the solver solves next, from tag point sets arriving in any order.

    Phases are solved in order, each once (warm-started from the previous one). Phase t is
    released when every expected slice's set for t is in, or when a later phase is complete (the
    missing slice is not coming in time), or when the caller forces it.

    Parameters
    ----------
    assembler : PhaseAssembler, optional
        The per-phase buffer of sets (a new one by default).

    """

    STALE, DUPLICATE, NEW = 'stale', 'duplicate', 'new'

    def __init__(self, assembler=None):
        if assembler is None:
            from mlv_ros.core.tracking import PhaseAssembler

            assembler = PhaseAssembler()
        self.assembler = assembler
        self.next_phase = 0  # the phase solved next
        self.num_phases = 0  # the study's phases, as the sets say (0: none seen yet)

    def add(self, points: TagPointSet) -> str:
        """
        Take a tag point set.

        Parameters
        ----------
        points : TagPointSet
            One slice's points at one phase.

        Returns
        -------
        str
            :attr:`STALE` (its phase was solved already: ignored), :attr:`DUPLICATE` (it
            replaced a set held for the same slice and phase) or :attr:`NEW`.

        """
        self.num_phases = max(self.num_phases, int(points.num_phases))
        if points.phase_index < self.next_phase:
            return self.STALE
        return self.DUPLICATE if self.assembler.add(points) else self.NEW

    @property
    def finished(self) -> bool:
        """Whether every phase of the study has been released (False before any set)."""
        return self.next_phase >= max(self.num_phases, 1)

    def waiting(self) -> bool:
        """Whether the next phase holds sets (so forcing it would release something)."""
        return bool(self.assembler.sets(self.next_phase))

    def ready(self, force: bool = False) -> Release | None:
        """
        Return the phase to solve now, or None while it must wait.

        Parameters
        ----------
        force : bool
            Release the next phase even though it is incomplete and no later phase is complete
            (the input has been quiet for long).

        Returns
        -------
        Release or None
            The next phase; call :meth:`done` once it is solved (or given up).

        """
        if not self.num_phases or self.next_phase >= self.num_phases:
            return None
        p, asm = self.next_phase, self.assembler
        complete = asm.complete(p)
        if not (complete or force or any(asm.complete(q) for q in asm.phases if q > p)):
            return None
        return Release(p, asm.sets(p), complete)

    def done(self, phase: int) -> None:
        """
        Drop ``phase``'s sets and move on to the next phase.

        Parameters
        ----------
        phase : int
            The phase :meth:`ready` released.

        """
        self.assembler.phases.pop(phase, None)
        self.next_phase = phase + 1


class Slot(NamedTuple):
    """
    One phase of a slice, leaving :class:`InOrderBuffer` in order.

    Attributes
    ----------
    phase : int
        The phase index.
    item : object
        What was offered for it; None when the phase never came and is skipped.

    """

    phase: int
    item: object


class InOrderBuffer:
    """
    Per-slice buffer releasing each slice's items in phase order.

    Parameters
    ----------
    max_pending : int
        Later phases allowed to wait for a missing one; when that many wait, the missing phase
        is skipped (>= 1).

    Raises
    ------
    ValueError
        ``max_pending`` < 1.

    """

    def __init__(self, max_pending: int):
        if max_pending < 1:
            raise ValueError(f'max_pending must be at least 1, got {max_pending}')
        self.max_pending = int(max_pending)
        self.next_phase: dict = {}  # slice key → the phase it releases next
        self.pending: dict = {}  # slice key → {phase: item} waiting for an earlier phase

    def expects(self, key: Hashable, phase: int) -> bool:
        """
        Check whether ``phase`` is the slot ``key`` releases next and nothing holds it yet.

        Parameters
        ----------
        key : hashable
            The slice, e.g. ``(view, slice_index)``.
        phase : int
            The phase index.

        Returns
        -------
        bool
            True when a stand-in for that phase may be put out at once (:meth:`fill`).

        """
        return phase == self.next_phase.get(key, 0) and phase not in self.pending.get(key, {})

    def offer(self, key: Hashable, phase: int, item) -> bool:
        """
        Hold ``item`` as ``key``'s phase ``phase``.

        Parameters
        ----------
        key : hashable
            The slice.
        phase : int
            The phase index.
        item : object
            What to release for that phase (not None).

        Returns
        -------
        bool
            False (nothing held) when the phase was released already or is held already.

        """
        waiting = self.pending.setdefault(key, {})
        if phase < self.next_phase.setdefault(key, 0) or phase in waiting:
            return False
        waiting[phase] = item
        return True

    def fill(self, key: Hashable, phase: int) -> None:
        """
        Count ``phase`` (the slot :meth:`expects`) as released by a stand-in put out elsewhere.

        Parameters
        ----------
        key : hashable
            The slice.
        phase : int
            The phase index.

        """
        self.next_phase[key] = phase + 1

    def drain(self, key: Hashable) -> Iterator[Slot]:
        """
        Release ``key``'s phases that are due, in order.

        Parameters
        ----------
        key : hashable
            The slice.

        Yields
        ------
        Slot
            The next phase with its item, or with None when it is skipped as missing (because
            ``max_pending`` later phases wait for it).

        """
        waiting = self.pending.get(key, {})
        while waiting:
            nxt = self.next_phase[key]
            if nxt not in waiting:
                if len(waiting) < self.max_pending:
                    return
                self.next_phase[key] = nxt + 1
                yield Slot(nxt, None)
                continue
            item = waiting.pop(nxt)
            self.next_phase[key] = nxt + 1
            yield Slot(nxt, item)


class StampPairer:
    """
    Pair items of two streams by key (a header stamp), with bounded memory.

    Parameters
    ----------
    max_unpaired : int
        Items each side holds while waiting for their pair; beyond it the oldest go (>= 1).
    sides : tuple of str
        The names of the two streams; pairs come out in the order the first one's items came.

    Raises
    ------
    ValueError
        ``max_unpaired`` < 1.

    """

    def __init__(self, max_unpaired: int, sides: tuple = ('cloud', 'state')):
        if max_unpaired < 1:
            raise ValueError(f'max_unpaired must be at least 1, got {max_unpaired}')
        self.max_unpaired = int(max_unpaired)
        self.held: dict = {side: {} for side in sides}  # side → {key: item}, oldest first
        self._first, self._second = sides

    def add(self, side: str, key: Hashable, item) -> None:
        """
        Hold ``item`` on ``side`` until its pair is in.

        Parameters
        ----------
        side : str
            One of the two sides given at construction.
        key : hashable
            What pairs it (a stamp); an item already held under it is replaced.
        item : object
            The item.

        """
        self.held[side][key] = item

    def trim(self, side: str) -> list:
        """
        Drop ``side``'s oldest items beyond ``max_unpaired``.

        Parameters
        ----------
        side : str
            One of the two sides.

        Returns
        -------
        list
            The keys dropped, oldest first.

        """
        held, dropped = self.held[side], []
        while len(held) > self.max_unpaired:
            key = next(iter(held))
            held.pop(key)
            dropped.append(key)
        return dropped

    def pairs(self) -> list:
        """
        Take every complete pair out.

        Returns
        -------
        list of (key, first, second)
            In the order the first side's items arrived.

        """
        first, second = self.held[self._first], self.held[self._second]
        return [(k, first.pop(k), second.pop(k)) for k in [k for k in first if k in second]]

    def discard(self, key: Hashable) -> dict:
        """
        Drop whatever is held for ``key`` on either side.

        Parameters
        ----------
        key : hashable
            The key.

        Returns
        -------
        dict
            ``{side: item}`` of what was held.

        """
        return {s: h.pop(key) for s, h in self.held.items() if key in h}
