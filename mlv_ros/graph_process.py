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
A node of ``mlv-ros run``'s graph in a process of its own.

So that it computes on another core than the rest of the graph (the tag detector beside the
registration and the solver).

The run spawns the child (:meth:`ChildNode.spawn`: the same interpreter and environment) before it
imports its own nodes, so that the child imports the node classes meanwhile, on the other core;
:meth:`ChildNode.start` then hands it its node. The run talks to it over the child's stdin and
stdout, one JSON object a line:

- run → child: the node's configuration (name, ROS domain, namespace, parameters file,
  overrides, logging threshold), then ``{"study": ID, "run": RUN_ID}`` (the study every node keeps
  to; the node spins only after it), then ``{"stop": true, "drain": true}`` (or end of file: the
  run is gone); ``"drain": false`` ends it without taking what is still queued (the run has
  every result already).
- child → run: ``{"event": "started"}`` or ``{"event": "start_failed", "reason": ...}``,
  ``{"event": "ready"}``, then the node's counters whenever they change (at most every 0.1 s;
  :data:`STATE_FIELDS`), and last ``{"event": "stopped", ...}`` with the final counters, or
  ``{"event": "crashed", "reason": ...}`` when a callback raised.

The child's own log lines go to stderr, as the run's do. It is in a session of its own, so a
terminal's Ctrl-C reaches the run only, which stops it once the phases in flight are done; if
the run dies, end of file on stdin stops the child.

:class:`ChildNode` stands in the run for the node: the counters and statuses ``mlv-ros run``
reads of its nodes (:meth:`progress`, ``diagnostics_sent``, ``failure``,
``last_error``, ``status``, ``other_studies``), a ``study`` to adopt, and ``crash`` (why the
process ended, when it ended on its own or a callback raised).
"""

from __future__ import annotations

from collections import Counter
import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

STATE_FIELDS = ('messages_handled', 'diagnostics_sent', 'published', 'blocked')
REPORT_PERIOD_S = 0.1
DRAIN_QUIET_S = 0.2  # as run_node: queued messages are taken until none came for this long


def _status_dict(status) -> dict | None:
    if status is None:
        return None
    level = status.level
    return {
        'level': level[0] if isinstance(level, (bytes, bytearray)) else int(level),
        'name': status.name,
        'message': status.message,
        'hardware_id': status.hardware_id,
        'values': [[kv.key, kv.value] for kv in status.values],
    }


def _status_msg(d: dict | None):
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

    if d is None:
        return None
    return DiagnosticStatus(
        level=bytes([int(d['level'])]),
        name=d['name'],
        message=d['message'],
        hardware_id=d['hardware_id'],
        values=[KeyValue(key=k, value=v) for k, v in d['values']],
    )


class _Study:
    """``node.study`` of a child: adopting a study sends it and waits until the node has it."""

    def __init__(self, child: 'ChildNode'):
        self._child = child
        self.study_id = self.run_id = ''

    def adopt(self, study_id: str, run_id: str = '') -> None:
        self.study_id, self.run_id = study_id, run_id
        self._child._adopt(study_id, run_id)


def child_env() -> dict:
    """Return this process's environment with the directory holding ``mlv_ros`` on the path."""
    import mlv_ros

    env = dict(os.environ)
    root = str(Path(mlv_ros.__file__).resolve().parents[1])
    env['PYTHONPATH'] = os.pathsep.join(
        [root, *([env['PYTHONPATH']] if env.get('PYTHONPATH') else [])]
    )
    return env


class ChildNode:
    """A graph node running in a child process (see the module's docstring)."""

    def __init__(self, name: str, proc: subprocess.Popen):
        self.name, self.proc = name, proc
        self.study = _Study(self)
        self.messages_handled = self.diagnostics_sent = self.published = self.blocked = 0
        self.failure: str | None = None
        self.crash: str | None = None  # why the process ended on its own, or a callback raised
        self.last_error = None
        self.status = None
        self.other_studies: Counter = Counter()
        self.streams: dict = {}
        self._events: dict[str, threading.Event] = {
            e: threading.Event() for e in ('started', 'start_failed', 'ready', 'stopped', 'eof')
        }
        self.start_error: str | None = None
        self._reader = threading.Thread(target=self._read, name=f'{name}-child', daemon=True)
        self._reader.start()

    @staticmethod
    def spawn() -> subprocess.Popen:
        """
        Start a child process that imports the graph's node classes and waits for its node.

        The child runs this interpreter, this environment, with the directory holding ``mlv_ros``
        on its path. It imports first and reads its configuration after, so a run spawns it
        before importing its own nodes and both import at once (:meth:`start` hands it the
        node). End one that was never handed a node with :func:`end_spawned`.

        Returns
        -------
        subprocess.Popen
            The process, its stdin and stdout pipes open, in text mode.

        """
        return subprocess.Popen(
            [sys.executable, '-m', 'mlv_ros.graph_process'],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=child_env(),
            text=True,
            start_new_session=True,
        )

    @classmethod
    def start(
        cls,
        name: str,
        domain_id: int,
        namespace: str,
        params_file: Path,
        overrides: dict,
        proc: subprocess.Popen | None = None,
    ) -> 'ChildNode':
        """
        Start node ``name`` in a child process: ``proc`` from :meth:`spawn`, or a new one.

        Parameters
        ----------
        name : str
            The node (:func:`_node_classes`).
        domain_id : int
            The ROS domain it talks on.
        namespace : str
            Its namespace.
        params_file : Path
            The graph's parameters file.
        overrides : dict
            Its parameters over the file's.
        proc : subprocess.Popen, optional
            A process :meth:`spawn` started that has no node yet (default: spawn one now).

        Returns
        -------
        ChildNode
            The node's stand-in; :meth:`wait_started` says whether it started.

        """
        from rclpy.logging import get_logger_effective_level

        child = cls(name, proc if proc is not None else cls.spawn())
        child._send(
            {
                'node': name,
                'domain_id': int(domain_id),
                'namespace': namespace,
                'params_file': str(params_file),
                'overrides': overrides,
                # the run's logging threshold (e.g. WARN: the console shows no INFO lines)
                'log_level': int(get_logger_effective_level('')),
            }
        )
        return child

    # ------------------------------------------------------------------ run side
    def _send(self, obj: dict) -> None:
        try:
            self.proc.stdin.write(json.dumps(obj) + '\n')
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError, ValueError):
            pass  # the child is gone: its reader says why

    def _read(self) -> None:
        for line in self.proc.stdout:
            try:
                msg = json.loads(line)
            except ValueError:
                continue
            event = msg.get('event')
            for key in STATE_FIELDS:
                if key in msg:
                    setattr(self, key, int(msg[key]))
            if 'failure' in msg:
                self.failure = msg['failure']
            if 'last_error' in msg:
                self.last_error = _status_msg(msg['last_error'])
            if 'status' in msg:
                self.status = _status_msg(msg['status'])
            if 'other_studies' in msg:
                self.other_studies = Counter(msg['other_studies'])
            if event == 'start_failed':
                self.start_error = msg.get('reason', 'could not start')
            elif event == 'crashed':
                self.crash = msg.get('reason', 'raised')
            if event in self._events:
                self._events[event].set()
        rc = self.proc.wait()
        if (
            not self._events['stopped'].is_set()
            and self.crash is None
            and self.start_error is None
        ):
            why = f'killed by {signal.Signals(-rc).name}' if rc < 0 else f'exit status {rc}'
            self.crash = f'its process ended unexpectedly ({why})'
        self._events['eof'].set()

    def progress(self) -> dict:
        """Return the node's counters as :meth:`GraphNode.progress` does, as last reported."""
        return {
            'received': int(self.messages_handled),
            'published': int(self.published),
            'blocked': int(self.blocked),
        }

    def wait_started(self, timeout: float = 120.0) -> str | None:
        """Block until the node is created; returns why it could not start, else None."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self._events['started'].wait(0.05):
                return None
            if self.start_error or self._events['eof'].is_set():
                return (
                    self.start_error or self.crash or 'its process ended before the node started'
                )
        return f'not started after {timeout:g} s'

    def _adopt(self, study_id: str, run_id: str, timeout: float = 30.0) -> None:
        self._send({'study': study_id, 'run': run_id})
        end = time.monotonic() + timeout
        while time.monotonic() < end and not self._events['eof'].is_set():
            if self._events['ready'].wait(0.05):
                return

    @property
    def done(self) -> bool:
        return self._events['eof'].is_set()

    def request_stop(self, drain: bool = True) -> None:
        """
        Ask the node to end, without waiting (:meth:`stop` waits).

        Parameters
        ----------
        drain : bool
            Take and publish what is queued first (until nothing came for
            :data:`DRAIN_QUIET_S`); False when the run knows every result is in.

        """
        if self.proc.poll() is None and not self.proc.stdin.closed:
            self._send({'stop': True, 'drain': bool(drain)})
            try:
                self.proc.stdin.close()
            except OSError:
                pass

    def stop(self, timeout: float = 10.0) -> None:
        """Let the node take what is queued, then end the process (killed after ``timeout``)."""
        if self.proc.poll() is None:
            self.request_stop()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._events['eof'].wait(5.0)  # the last counters are read

    def destroy_node(self) -> None:
        self.stop()


def end_spawned(proc: subprocess.Popen) -> None:
    """End a process from :meth:`ChildNode.spawn` that was never handed a node."""
    if proc.poll() is None:
        proc.kill()
    proc.wait()
    for pipe in (proc.stdin, proc.stdout):
        try:
            pipe.close()
        except OSError:
            pass


# ---------------------------------------------------------------------- child side
def _node_classes() -> dict:
    from mlv_ros.nodes.tag_detector import TagDetector

    return {'tag_detector': TagDetector}


def _emit(out, obj: dict) -> None:
    out.write(json.dumps(obj) + '\n')
    out.flush()


def _state(node) -> dict:
    state = {k: int(getattr(node, k, 0)) for k in STATE_FIELDS}
    state['failure'] = node.failure
    state['last_error'] = _status_dict(node.last_error)
    state['status'] = _status_dict(node.status)
    state['other_studies'] = dict(node.other_studies)
    return state


def main() -> int:
    # The protocol owns stdout: anything else printed there goes to stderr instead.
    out = os.fdopen(os.dup(sys.stdout.fileno()), 'w')
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    config = json.loads(sys.stdin.readline() or '{}')
    from mlv_ros.cli import error_text
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    name = config.get('node', '')
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(config.get('domain_id', 0)))
    if config.get('log_level') is not None:
        from rclpy.logging import LoggingSeverity, set_logger_level

        set_logger_level('', LoggingSeverity(int(config['log_level'])))
    node = None
    try:
        try:
            node = _node_classes()[name](
                context=ctx,
                namespace=config.get('namespace', '/'),
                cli_args=['--ros-args', '--params-file', config['params_file']],
                parameter_overrides=[
                    Parameter(k, value=v) for k, v in (config.get('overrides') or {}).items()
                ],
            )
        except Exception as exc:
            _emit(out, {'event': 'start_failed', 'reason': error_text(exc)})
            return 2
        _emit(out, {'event': 'started'})
        line = sys.stdin.readline()
        if not line:
            return 0  # the run ended while starting
        study = json.loads(line)
        node.study.adopt(study.get('study', ''), study.get('run', ''))
        _emit(out, {'event': 'ready'})

        drain = [True]  # what the stop line says (end of file: the run is gone, drain)

        def watch_stdin():
            for text in sys.stdin:
                line = json.loads(text or '{}')
                if line.get('stop'):
                    drain[0] = bool(line.get('drain', True))
                    break
            stop.set()

        threading.Thread(target=watch_stdin, daemon=True).start()
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        crashed = _spin(ex, node, stop, out)
        if crashed is None and not node.done and drain[0]:
            crashed = _drain(ex, node)
        if crashed is not None:
            _emit(out, {'event': 'crashed', 'reason': crashed, **_state(node)})
            return 1
        _emit(out, {'event': 'stopped', **_state(node)})
        return 1 if node.failure else 0
    finally:
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()


def _spin(ex, node, stop: threading.Event, out) -> str | None:
    """
    Spin the node until stopped or done, reporting its counts as they change.

    Parameters
    ----------
    ex : rclpy.executors.Executor
        Holds the node.
    node : GraphNode
        The node.
    stop : threading.Event
        Set by a signal or the parent's stop line.
    out : file
        The protocol stream (:func:`_emit`).

    Returns
    -------
    str or None
        Why a callback raised (the node is gone), or None.

    """
    from mlv_ros.cli import error_text

    last, sent_at = None, 0.0
    while not stop.is_set() and not node.done:
        try:
            ex.spin_once(timeout_sec=0.05)
        except Exception as exc:  # a callback raised: the node is gone
            return error_text(exc)
        state = _state(node)
        if state != last and time.monotonic() - sent_at >= REPORT_PERIOD_S:
            _emit(out, {'event': 'counts', **state})
            last, sent_at = state, time.monotonic()
    return None


def _drain(ex, node) -> str | None:
    """Take and publish what arrived before the stop, until quiet; say why it crashed, or None."""
    from mlv_ros.cli import error_text

    handled, quiet_since = node.messages_handled, time.monotonic()
    while time.monotonic() - quiet_since < DRAIN_QUIET_S:
        try:
            ex.spin_once(timeout_sec=0.05)
        except Exception as exc:
            return error_text(exc)
        if node.messages_handled != handled:
            handled, quiet_since = node.messages_handled, time.monotonic()
    return None


if __name__ == '__main__':
    from mlv_ros.threads import compute_threads

    _node_classes()  # imported first: OpenCV's pool is held only if loaded before
    with compute_threads():
        raise SystemExit(main())
