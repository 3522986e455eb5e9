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
The phantom's frames simulated in a process of their own, in the order they are published.

So that simulating a study (~17 ms a 256² frame, ~4.7 s for the default study) computes on
another core than the nodes of the run's process (registration, solver, recorder), while the
frames already simulated go out. The frame source starts it (:class:`RenderProcess`) with the
study's parameters and the frames' order; the child renders every frame with
:class:`~mlv_ros.core.sim.study.StudyRenderer` (the same images as in one process, to the bit)
and writes each to its stdout as it is done:

- child → parent, per frame: a header ``<iii`` (index in the order, rows, cols) and the image,
  float32, C order; on a failure: index -1, then the length of a UTF-8 reason and the reason.

It imports no ROS (numpy/scipy and :mod:`mlv_ros.core.sim` only: ~0.6 s, ~120 MB). The parent
reads it on a thread, which hands each image to a callback; end of file before the last frame
is a failure (the reason names the exit status).
"""

from __future__ import annotations

import contextlib
import json
import os
import struct
import subprocess
import sys
import threading
from typing import Callable

HEADER = struct.Struct('<iii')
# Most bytes of frames handed to the parent and not yet published (:meth:`RenderProcess.taken`):
# the child waits (its pipe full) beyond that. While the run's executor is busy (the
# registration), frames rendered ahead wait in the parent; a bound in bytes keeps a large study
# (e.g. 40 phases x 20 slices of 512^2 float32, 840 MB) from piling up, while the default study
# (275 frames of 256^2, 72 MB) never waits: using the idle core early pays on 2 cores. Measured on
# the default study at load 1-2, 4 rounds alternated: whole study 12.6-13.0 s unbounded against
# 12.7-14.2 s with a 64-frame (16 MB) bound, paired median 1.08 (docs/benchmarks.md, issue 17);
# the bound's saving, ~50 MB summed RSS (673 against 722 MB), is not needed for the 800 MB must.
RENDER_AHEAD_BYTES = 128 * 2**20


def processes_allowed() -> bool:
    """Return whether a run may compute in several processes (>= 2 cores, no one-process flag)."""
    return (
        os.environ.get('MLV_ROS_ONE_PROCESS', '').strip() in ('', '0')
        and (os.cpu_count() or 1) >= 2
    )


class RenderProcess:
    """
    Simulate a study's frames in a child process; hand each image to ``on_frame`` as it comes.

    Parameters
    ----------
    study : dict
        :class:`~mlv_ros.core.sim.study.StudyRenderer`'s keyword arguments (JSON-serialisable:
        ``preset`` a name or path).
    keys : list of tuple of int
        ``(view, slice_index, phase)`` of every frame to render, in this order.
    on_frame : callable
        ``on_frame(index, image)`` on the reader thread, for each frame in order (``image``
        float32 (rows, cols)); at most :data:`RENDER_AHEAD_BYTES` of frames ahead of
        :meth:`taken` (at least one frame).
    on_failure : callable
        ``on_failure(reason)`` on the reader thread, once, if the child fails or ends early.

    """

    def __init__(
        self,
        study: dict,
        keys: list,
        on_frame: Callable[[int, object], None],
        on_failure: Callable[[str], None],
    ):
        from mlv_ros.graph_process import child_env

        self.total = len(keys)
        self.received = 0
        self.failure: str | None = None
        self._closed = False
        self._on_frame, self._on_failure = on_frame, on_failure
        self._ahead = 0  # frames handed over and not yet taken()
        self._limit: int | None = None  # frames the byte budget holds (known at the first frame)
        self._room = threading.Condition()
        self.proc = subprocess.Popen(
            [sys.executable, '-m', 'mlv_ros.render_process'],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=child_env(),
            start_new_session=True,  # a terminal's Ctrl-C reaches the run, which ends it
        )
        job = {'study': study, 'keys': [list(k) for k in keys]}
        try:
            self.proc.stdin.write(json.dumps(job).encode())
            self.proc.stdin.close()
        except OSError:  # BrokenPipeError: the child is gone; the reader says why
            with contextlib.suppress(OSError):
                self.proc.stdin.close()
        self._reader = threading.Thread(target=self._read, name='render-process', daemon=True)
        self._reader.start()

    def _read(self) -> None:
        import numpy as np

        out = self.proc.stdout
        try:
            while self.received < self.total:
                with self._room:
                    while self._limit is not None and self._ahead >= self._limit:
                        self._room.wait(timeout=0.2)
                        if self._closed:
                            return
                head = out.read(HEADER.size)
                if len(head) < HEADER.size:
                    break
                index, rows, cols = HEADER.unpack(head)
                if self._limit is None and index >= 0:
                    self._limit = max(1, RENDER_AHEAD_BYTES // (4 * rows * cols))
                if index < 0:
                    self.failure = out.read(rows).decode('utf-8', 'replace')
                    break
                data = out.read(4 * rows * cols)
                if len(data) < 4 * rows * cols:
                    break
                with self._room:
                    self._ahead += 1
                self._on_frame(index, np.frombuffer(data, np.float32).reshape(rows, cols))
                self.received += 1
        finally:
            out.close()
            rc = self.proc.wait()
            if self.received < self.total and not self._closed:
                why = f'exit status {rc}' if rc >= 0 else f'killed by signal {-rc}'
                self.failure = self.failure or f'the render process ended early ({why})'
                self._on_failure(self.failure)

    def taken(self) -> None:
        """Say that a frame handed over is published and dropped: one more may come."""
        with self._room:
            self._ahead -= 1
            self._room.notify()

    def close(self) -> None:
        """End the child if it still runs and wait for it and its reader (no failure reported)."""
        self._closed = True
        if self.proc.poll() is None:
            self.proc.kill()
        self._reader.join(timeout=5.0)


def main() -> int:
    """Render the frames asked for on stdin (see the module's docstring) to stdout."""
    out = sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing but frames goes to the parent's pipe
    try:
        # Imported before the job is read: the parent writes it at once, the imports take longer.
        from mlv_ros.core.sim.study import StudyRenderer
        from mlv_ros.threads import compute_threads

        job = json.loads(sys.stdin.buffer.read())

        with compute_threads():
            renderer = StudyRenderer(**job['study'])
            for i, key in enumerate(job['keys']):
                img = renderer.frame(*key).image
                out.write(HEADER.pack(i, *img.shape))
                out.write(img.tobytes())
                out.flush()
    except BrokenPipeError:
        return 1  # the parent is gone
    except Exception as exc:  # any failure is reported to the parent, which reports it
        reason = f'{type(exc).__name__}: {exc}'.encode()
        out.write(HEADER.pack(-1, len(reason), 0) + reason)
        out.flush()
        return 1
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
