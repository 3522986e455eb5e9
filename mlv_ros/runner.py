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
Run the whole graph on one input and record it: what ``mlv-ros run`` and ``mlv-ros demo`` share.

The tag detector runs in a process of its own (:mod:`mlv_ros.graph_process`), the other nodes in
this process (one executor); :func:`run_graph` starts them, watches them, ends the run and writes
``summary.json`` (:mod:`mlv_ros.console` shows it).

A run claims its ROS domain: a private one (an flock, :mod:`mlv_ros.domain`) unless the user
chose one (``--domain-id`` or ``ROS_DOMAIN_ID``); a chosen domain on which discovery finds a
node of another mlv_ros graph in the same namespace is refused. ``namespace`` puts every node,
and so every graph topic, under ``/NS`` (``/NS/mlv/frames``; the recording holds those names), so
graphs in different namespaces share a domain. Every node of the graph keeps to the study the
input carries (``study_id``) and reports and ignores messages of any other, so two graphs that do
meet on one domain cannot mix.

The run watches its nodes: one that cannot start, gives up, raises, or leaves the graph with
nothing to do ends the run at once with that node's reason. SIGINT/SIGTERM stop the input, let
the phases in flight finish (at most ``grace`` seconds; a second signal stops waiting), close
the recording with everything received and mark it incomplete.
"""

from __future__ import annotations

from dataclasses import dataclass
import json
import os
from pathlib import Path
import signal
import tempfile
import threading
import time
from typing import Callable

from mlv_ros import graph_table
from mlv_ros.cli import error_text
import yaml


GRAPH = list(graph_table.RUN_NODES)  # downstream first (mlv_ros/graph_table.py)
# Node names of an mlv_ros graph: one of them on a domain means a graph is using it.
GRAPH_NODE_NAMES = (*GRAPH, 'replay')
# Nodes run in a child process each (on a machine with more than one core), so that they compute
# beside the others: the tag detector's work per frame is as large as the rest of the graph's.
# Measured on the 2-core machine, `bench pipeline` (default study), alternated: 20.9, 19.9,
# 23.1 s with the tag detector in its own process, 23.4, 23.3 s all in one (load 1.4-2.5); the
# graph in one process with a MultiThreadedExecutor instead took 44 s (the GIL). Set
# MLV_ROS_ONE_PROCESS=1 to keep every node in the run's process.
CHILD_NODES = ('tag_detector',)
# How long discovery is given to show another graph's nodes before a chosen domain counts as free
# (on one host they show within about 0.1 s; longer when discovery reaches other hosts).
DOMAIN_PROBE_S = 1.0
DOMAIN_PROBE_NETWORK_S = 2.0
PROBE_PREFIX = '_mlv_ros_run_'  # the node a run looks at its domain with (see graph_nodes_on)
EXIT_INCOMPLETE, EXIT_USAGE, EXIT_UNTRACKED = 1, 2, 3
SIGNAL_EXIT = {signal.SIGINT: 130, signal.SIGTERM: 143}  # 128 + signal number, as shells report it
QUIET_S = 0.5  # no graph activity for this long: the phases in flight are done
DRAIN_QUIET_S, DRAIN_MAX_S = 0.3, 3.0  # the recorder's last take of what is queued
# The nodes whose counters say when a run is done: source, solver, analyzer.
GRAPH_ROLES = ('frame_source', 'meshless_solver', 'motion_analyzer')


class RunStartError(ValueError):
    """
    Error raised when the graph could not start.

    A node refused its parameters, the input has no frames, or the run directory cannot be written;
    nothing was recorded and nothing is left behind.
    """


class DomainBusyError(RunStartError):
    """Another mlv_ros graph runs on the ROS domain the run was asked to use."""


class RunInterrupted(Exception):
    """SIGINT/SIGTERM while the graph was starting (nothing recorded, nothing left behind)."""

    def __init__(self, signum: int):
        self.signum = signum
        self.name = signal.Signals(signum).name
        super().__init__(f'interrupted by {self.name} while starting')


class _Signals:
    """
    SIGINT/SIGTERM handling for one run.

    While the graph starts the first signal raises :class:`RunInterrupted` (loading a study can
    take a while, and there is nothing to keep yet). Once it runs a signal only sets a flag,
    which the run loop turns into a clean stop; the second stops waiting for the phases in
    flight; the third ends the process at once (the recording is then unfinished: ``mlv-ros
    recover``).
    """

    def __init__(self):
        self.received: list[int] = []
        self.starting = True
        self._previous: dict = {}

    def install(self) -> '_Signals':
        if threading.current_thread() is threading.main_thread():  # Python allows no other
            for sig in SIGNAL_EXIT:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def _handle(self, signum, _frame) -> None:
        self.received.append(signum)
        if self.starting:
            self.starting = False  # raise once: the clean-up runs with signals only counted
            raise RunInterrupted(signum)
        if len(self.received) >= 3:
            self.restore()
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)

    @property
    def first(self) -> str | None:
        return signal.Signals(self.received[0]).name if self.received else None


def node_parameters(params_file: Path, overrides: dict, names=GRAPH) -> dict:
    """
    Return each graph node's rclpy Node keyword arguments (parameters file and overrides).

    {node: rclpy Node keyword arguments} giving each graph node the parameters file and the
    overrides {node: {name: value}} (which win over the file).

    The file is handed to rcl as ``--ros-args --params-file`` does, so its keys mean what they
    mean to every ROS node: ``/**`` (any node in any namespace), ``/**/frame_source`` (that node
    in any namespace), ``frame_source`` (that node in the root namespace only),
    ``/study2/frame_source`` or the nested ``study2: {frame_source: ...}``; of several keys
    matching a node, the later in the file wins.
    """
    from rclpy.parameter import Parameter

    return {
        node: {
            'cli_args': ['--ros-args', '--params-file', str(params_file)],
            'parameter_overrides': [
                Parameter(k, value=v) for k, v in overrides.get(node, {}).items()
            ],
        }
        for node in names
    }


def node_class(name: str):
    """
    Return the GraphNode subclass of graph node ``name`` (its module imported).

    Parameters
    ----------
    name : str
        A node of :data:`mlv_ros.graph_table.NODES`.

    Returns
    -------
    type
        The class, e.g. ``MeshlessSolver`` for ``meshless_solver``.

    """
    import importlib

    entry = next(n for n in graph_table.NODES if n.name == name)
    return getattr(importlib.import_module(f'mlv_ros.nodes.{name}'), entry.node_class)


def graph_nodes_on(domain_id: int, wait_s: float | None = None, namespace: str = '/') -> list[str]:
    """
    Return the mlv_ros graph nodes that discovery finds in ``namespace`` on a ROS domain.

    The nodes of an mlv_ros graph (:data:`GRAPH_NODE_NAMES`) in ``namespace`` on ROS domain
    ``domain_id``, looked for within ``wait_s`` seconds (returns as soon as it finds one).

    A graph in another namespace talks on other topics (``/a/mlv/frames``, ``/b/mlv/frames``):
    it is no conflict, and not counted. The look itself is a hidden node in ``namespace`` named
    for when it started (``_mlv_ros_run_<ns>_<pid>``), so two runs that look at once in one
    namespace see each other: the one that started later counts the earlier one's as a graph
    there (and is refused), the earlier one goes on.

    Parameters
    ----------
    domain_id : int
        The domain to look at (0..232).
    wait_s : float, optional
        Discovery time; default :data:`DOMAIN_PROBE_S`, or :data:`DOMAIN_PROBE_NETWORK_S` when
        discovery is not kept on this host (``ROS_AUTOMATIC_DISCOVERY_RANGE`` other than
        ``LOCALHOST``, or ``ROS_STATIC_PEERS``).
    namespace : str
        The namespace to look in (``/`` the root; ``study2`` is ``/study2``).

    Returns
    -------
    list of str
        Their fully qualified names, sorted (empty: the domain looks free).

    """
    import rclpy
    from rclpy.node import Node

    if wait_s is None:
        local = os.environ.get(
            'ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST'
        ).upper() == 'LOCALHOST' and not os.environ.get('ROS_STATIC_PEERS')
        wait_s = DOMAIN_PROBE_S if local else DOMAIN_PROBE_NETWORK_S
    me = (time.time_ns(), os.getpid())
    from mlv_ros.qos import full_namespace

    namespace = full_namespace(namespace)

    def earlier_run(name: str) -> bool:
        started, _, pid = name.removeprefix(PROBE_PREFIX).partition('_')
        if not name.startswith(PROBE_PREFIX) or not (started.isdigit() and pid.isdigit()):
            return False
        return (int(started), int(pid)) < me

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    node = None
    try:
        # Hidden (leading underscore), without parameter services or /rosout.
        node = Node(
            f'{PROBE_PREFIX}{me[0]}_{me[1]}',
            namespace=namespace,
            context=ctx,
            enable_rosout=False,
            start_parameter_services=False,
        )
        end = time.monotonic() + wait_s
        while True:
            found = sorted(
                {
                    f'{ns.rstrip("/")}/{name}'
                    for name, ns in node.get_node_names_and_namespaces()
                    if full_namespace(ns) == namespace
                    and (name in GRAPH_NODE_NAMES or earlier_run(name))
                }
            )
            if found or time.monotonic() >= end:
                return found
            time.sleep(0.02)
    finally:
        if node is not None:
            node.destroy_node()
        ctx.try_shutdown()


def busy_domain_text(domain_id: int, nodes: list[str], namespace: str = '/') -> str:
    """Return the line refusing a busy domain, saying how to pick another domain or namespace."""
    shown = ', '.join(
        'another mlv-ros run starting' if PROBE_PREFIX in n else n for n in nodes[:4]
    )
    shown += ', ...' if len(nodes) > 4 else ''
    where = 'the root namespace' if namespace == '/' else f'namespace {namespace}'
    return (
        f'ROS domain {domain_id} is busy: another mlv_ros graph is running on it in {where} '
        f'({shown}); '
        'choose another with --domain-id N or export ROS_DOMAIN_ID=N (0..232), or another '
        '--namespace NS, '
        f'or set no domain and mlv-ros run takes a free private one'
    )


def _chosen_domain(domain_id: int | None) -> tuple[int | None, bool]:
    """
    Return the domain the user chose and whether one was chosen.

    The domain is ``domain_id`` or ``$ROS_DOMAIN_ID``, or None when neither was given.
    """
    if domain_id is not None:
        return int(domain_id), True
    text = os.environ.get('ROS_DOMAIN_ID', '').strip()
    if not text:
        return None, False
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 232:
        raise RunStartError(
            f'ROS_DOMAIN_ID={text!r} is not a ROS domain id: set it to a number from 0 to 232, '
            'or unset it and mlv-ros run takes a free private one'
        )
    return value, True


def _prepare_out(out_dir: Path) -> list[Path]:
    """
    Create the run directory, check it takes files and return the directories created.

    The directories created come deepest first, for a failed start to remove.
    """
    if (out_dir / 'run.mcap').exists():
        raise FileExistsError(
            f'{out_dir} already holds a run (run.mcap): choose a new --out directory '
            '(runs are never overwritten)'
        )
    if out_dir.exists() and not out_dir.is_dir():
        raise RunStartError(
            f'--out {out_dir} is a file, not a directory: choose a new --out directory'
        )
    missing = [d for d in (out_dir, *out_dir.parents) if not d.exists()]
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out_dir):
            pass
    except OSError as exc:
        _remove_dirs(missing)
        raise RunStartError(
            f'cannot write in --out {out_dir}: {exc.strerror or exc}; '
            'choose a directory you can write to'
        ) from exc
    return missing


def _remove_dirs(created: list[Path]) -> None:
    for d in created:
        try:
            d.rmdir()
        except OSError:
            return  # not empty (or not ours to remove): keep it and its parents


def _raising_node(exc: BaseException, nodes: dict) -> str:
    """Name of the graph node whose callback raised ``exc`` (the innermost node method)."""
    found = 'a node'
    tb = exc.__traceback__
    while tb is not None:
        owner = tb.tb_frame.f_locals.get('self')
        for name, node in nodes.items():
            if owner is node:
                found = name
        tb = tb.tb_next
    return found


def _reason(node) -> str:
    """Why ``node`` is stuck: its latest ERROR, else its current status."""
    from mlv_ros.nodes.common import status_text

    return status_text(node.last_error or node.status)


def child_nodes() -> tuple[str, ...]:
    """
    Return the nodes a run starts in processes of their own.

    :data:`CHILD_NODES`; none on one core or with ``MLV_ROS_ONE_PROCESS=1``.
    """
    from mlv_ros.render_process import processes_allowed

    return CHILD_NODES if processes_allowed() else ()


def _stuck(nodes: dict) -> str | None:
    """Why the graph cannot go on, when one of its nodes gave up or is left with nothing to do."""
    for name, node in nodes.items():
        if getattr(node, 'crash', None):  # a node in a child process raised, or its process ended
            return f'{name} failed: {node.crash}'
    for name, node in nodes.items():
        if getattr(node, 'failure', None):
            return f'{name}: {node.failure}'
    # A node holding an input it cannot use (a failed registration, a registered model the
    # solver or analyzer cannot build on; frames no subscriber takes) waits for what this run
    # will not send.
    for name, node in nodes.items():
        if node.progress()['blocked']:
            return f'{name}: {_reason(node)}'
    return None


def _activity(nodes: dict) -> int:
    """
    Return a number that grows whenever the graph does something.

    It counts frames, tag points, phases and messages taken; /diagnostics heartbeats are left out.
    """
    return sum(p['received'] + p['published'] for p in (n.progress() for n in nodes.values()))


def _taken(node, topic: str) -> int:
    """Messages ``node`` has taken from ``topic``."""
    count = node.streams.get(topic)
    return count.received if count is not None else 0


def _statuses(nodes: dict) -> str:
    """Return the nodes' latest errors (or, without any, their warnings) on one line."""
    from mlv_ros.nodes.common import OK, status_text

    said = [
        f'{name}: {status_text(n.last_error)}'
        for name, n in nodes.items()
        if n.last_error is not None
    ]
    said = said or [
        f'{name}: {status_text(n.status)}'
        for name, n in nodes.items()
        if n.status is not None and n.status.level != OK
    ]
    return '; '.join(said) if said else 'no node reported a problem'


def _no_frames(src, source: dict) -> str:
    """Why the input gave no frame, for a start that ends there."""
    from mlv_ros import bagio, qos

    path = source.get('path', '')
    if source.get('source') == 'bag':
        try:
            topics = sorted(bagio.bag_topics(path))
        except (ValueError, OSError):
            topics = []
        has = (
            f' (its topics: {", ".join(topics[:6])}{", ..." if len(topics) > 6 else ""})'
            if topics
            else ''
        )
        return (
            f'--bag {path} has no {qos.FRAMES} messages{has}: give a recording made by mlv-ros '
            '(`mlv-ros run` or the recorder)'
        )
    if source.get('source') == 'dicom':
        problems = getattr(src, '_reports', [])
        first = (
            f'; first: {problems[0][1].get("file")}: {problems[0][1].get("reason")}'
            if problems
            else ''
        )
        return (
            f'--dicom {path}: no usable tagged cine image ({len(problems)} file(s) skipped{first})'
        )
    return f'the {source.get("source")} source produced no frames'


def run_graph(
    source: dict,
    out_dir: Path,
    params_file: Path | None = None,
    overrides: dict | None = None,
    timeout: float = 600.0,
    progress=print,
    domain_id: int | None = None,
    grace: float = 10.0,
    handle_signals: bool = True,
    namespace: str | None = None,
    live: dict | None = None,
    on_phase=None,
) -> dict:
    """
    Run the graph on ``source`` and record it to ``out_dir/run.mcap``.

    Parameters
    ----------
    source : dict
        ``{"source": "phantom"|"dicom"|"bag"|"pattern", ...}`` and any other frame_source
        parameters.
    out_dir : Path
        Run directory (created); must not hold a ``run.mcap``.
    params_file : Path, optional
        Graph parameters YAML (default ``config/graph.yaml``).
    overrides : dict, optional
        ``{node: {parameter: value}}`` over the file's values.
    timeout : float
        Give up after this many seconds.
    progress : callable
        Called with one line per event worth showing (phases analysed, an interruption).
    domain_id : int, optional
        The ROS domain the graph talks on; default ``ROS_DOMAIN_ID`` when the caller set it, else
        a private one claimed for this process (so parallel runs never mix). A domain chosen so
        is refused when another mlv_ros graph's node is on it (:func:`graph_nodes_on`).
    grace : float
        On SIGINT/SIGTERM, seconds to wait at most for the phases in flight.
    handle_signals : bool
        Take SIGINT/SIGTERM for a clean stop (only from the main thread).
    namespace : str, optional
        ROS namespace of every node (``study2`` or ``/study2``; default the root): the graph's
        topics resolve under it and are recorded so. Diagnostic statuses are then named by the
        nodes' fully qualified names (``diagnostic_updater.use_fqn``), since ``/diagnostics`` is
        shared. The domain check looks for another graph in this namespace only.
    live : dict, optional
        Serve the run to Foxglove: a ``live_view`` node (:mod:`mlv_ros.nodes.live_view`) with
        these parameters over the file's (e.g. ``{"port": 8765}``), started before the graph so
        it sees every phase; its URL is the first progress line after the start. A port that
        cannot be bound is a :class:`RunStartError`.
    on_phase : callable, optional
        Called with (phases analysed, phases in the study) once the graph runs and at each
        phase analysed (a progress bar).

    Returns
    -------
    dict
        The summary, also written to ``out_dir/summary.json``: counts, ``study_id``, ``complete``
        (every phase analysed and, for DICOM, nothing of the study left out), ``phases_complete``
        (every phase analysed), and ``interrupted`` (the signal's name) or ``failed`` (the reason)
        when the run did not end by itself. For a DICOM source also ``input_complete``,
        ``dicom_study`` (which study was taken and why), ``left_out`` and ``not_used``
        (``"path: reason"`` each).

    Raises
    ------
    FileExistsError
        ``out_dir`` already holds a run.
    RunStartError
        The graph could not start; nothing was recorded and nothing is left behind
        (:class:`DomainBusyError`: the chosen domain holds another mlv_ros graph).
    RunInterrupted
        SIGINT/SIGTERM while it was starting (nothing left behind either).

    """
    signals = _Signals()
    if handle_signals:
        signals.install()
    # The nodes of processes of their own start importing now, while this process imports its.
    spawned = _spawn_children()
    try:
        # OpenCV loaded first, so that its pools are held too (the registration's segmentation
        # runs here; so does the tag detector when it has no process of its own)
        import cv2  # noqa: F401

        if 'tag_detector' not in spawned:
            import mlv_ros.nodes.tag_detector  # noqa: F401
        from mlv_ros.threads import compute_threads

        with (
            compute_threads()
        ):  # the same motion as any other layout of the graph (mlv_ros/threads.py)
            return _run_graph(
                source,
                Path(out_dir),
                params_file,
                overrides,
                timeout,
                progress,
                domain_id,
                grace,
                signals,
                namespace,
                live,
                on_phase or (lambda done, total: None),
                spawned,
            )
    finally:
        _end_spawned(spawned)
        signals.restore()


def _spawn_children() -> dict:
    """
    Return {node: process} for the nodes that run in processes of their own (:func:`child_nodes`).

    Each process imports its node's class at once and waits for its configuration
    (:meth:`~mlv_ros.graph_process.ChildNode.spawn`), so that its imports (rclpy, OpenCV, scipy:
    about 1 s of CPU) run beside this process's instead of after them. None on a failed spawn:
    the node is then started as before, when its turn comes.
    """
    from mlv_ros.graph_process import ChildNode

    spawned = {}
    for name in child_nodes():
        try:
            spawned[name] = ChildNode.spawn()
        except OSError:
            pass  # started in its turn (_start_nodes), which reports why it cannot
    return spawned


def _end_spawned(spawned: dict) -> None:
    """End the spawned processes no node took (the run failed to start before it could)."""
    from mlv_ros.graph_process import end_spawned

    while spawned:
        end_spawned(spawned.popitem()[1])


@dataclass
class _Running:
    """
    A graph that runs: its executor, nodes, the study's phase count, where its lines go.

    Attributes
    ----------
    ex : SingleThreadedExecutor
        Spins the nodes of this process.
    nodes : dict
        Node name → node (a :class:`~mlv_ros.graph_process.ChildNode` for one in a process of its
        own).
    num_phases : int
        Phases of the study the frame source holds.
    t0 : float
        ``time.monotonic()`` when the context started.
    progress : callable
        Called with one line per event worth showing.
    on_phase : callable
        Called with (phases analysed, phases in the study).
    signals : _Signals
        The signals received.

    """

    ex: object
    nodes: dict
    num_phases: int
    t0: float
    progress: Callable
    on_phase: Callable
    signals: '_Signals'

    def phase_analysed(self, n: int) -> None:
        """Show that ``n`` phases are analysed."""
        self.progress(
            f'[mlv-ros] phase {n}/{self.num_phases} analysed ({time.monotonic() - self.t0:.1f} s)'
        )
        self.on_phase(n, self.num_phases)


def _graph_parameters(source, mcap, params_file, overrides, namespace, live):
    """
    Return the nodes to start, the namespace, the parameters file and each node's parameters.

    Parameters
    ----------
    source, params_file, namespace, live
        As :func:`run_graph`'s.
    mcap : Path
        The recording the recorder writes.
    overrides : dict or None
        As :func:`run_graph`'s (not modified).

    Returns
    -------
    names : list of str
        The nodes, downstream first (the live view first of all: it sees every phase).
    namespace : str
        The full namespace.
    params_path : Path
        The parameters file.
    params : dict
        Node name → its keyword arguments (:func:`node_parameters`).
    overrides : dict
        Node name → its parameters over the file's (those of a node in a process of its own).

    Raises
    ------
    RunStartError
        The parameters file is not one the nodes can read.

    """
    from mlv_ros import qos
    from mlv_ros.resources import config_file

    overrides = {k: dict(v) for k, v in (overrides or {}).items()}
    overrides.setdefault('frame_source', {}).update(source)
    overrides.setdefault('recorder', {})['output'] = str(mcap)
    names = GRAPH if live is None else ['live_view', *GRAPH]
    if live is not None:
        overrides['live_view'] = {**dict(live), **overrides.get('live_view', {})}
    namespace = qos.full_namespace(namespace)
    if namespace != '/':  # /diagnostics is shared: say which graph's node each status is
        for name in names:
            overrides.setdefault(name, {})['diagnostic_updater.use_fqn'] = True
    params_path = Path(params_file) if params_file else config_file('graph.yaml')
    bad_params = params_error(params_path)
    if bad_params:
        raise RunStartError(bad_params)
    return names, namespace, params_path, node_parameters(params_path, overrides, names), overrides


def _claimed_domain(domain_id: int | None, namespace: str) -> int:
    """
    Return the domain the run talks on: the one chosen, if no other graph is on it, or its own.

    Raises
    ------
    DomainBusyError
        A domain the user chose holds another mlv_ros graph in ``namespace``.

    """
    from mlv_ros.domain import claim_domain_id

    domain_id, chosen = _chosen_domain(domain_id)
    if not chosen:
        return claim_domain_id()
    # A domain the user chose may hold another graph (a second run, a launched one): refuse
    # it before anything is created. A claimed private one is this process's alone.
    busy = graph_nodes_on(domain_id, namespace=namespace)
    if busy:
        raise DomainBusyError(busy_domain_text(domain_id, busy, namespace))
    return domain_id


def _start_nodes(ex, ctx, nodes: dict, names, classes, start: dict, source: dict) -> None:
    """
    Start every node into ``nodes`` and have each keep to the input's study.

    Parameters
    ----------
    ex : SingleThreadedExecutor
        Spins the nodes of this process.
    ctx : rclpy.Context
        Their context.
    nodes : dict
        Filled with node name → node as each starts (what to destroy if one fails).
    names : list of str
        The nodes, downstream first, so every subscriber exists before frames flow.
    classes : dict
        Node name → its class (:func:`node_class`).
    start : dict
        ``domain_id``, ``namespace``, ``params_path``, ``params`` and ``overrides``
        (:func:`_graph_parameters`), and ``spawned``: {node: process} of
        :func:`_spawn_children` (each taken by its node).
    source : dict
        As :func:`run_graph`'s.

    Raises
    ------
    RunStartError
        A node could not start, or the input has no frames.

    """
    from mlv_ros.graph_process import ChildNode

    separate = child_nodes()
    for name in names:
        if name in separate:  # its process was spawned at the start: it is handed its node now
            try:
                nodes[name] = ChildNode.start(
                    name,
                    start['domain_id'],
                    start['namespace'],
                    start['params_path'],
                    start['overrides'].get(name, {}),
                    proc=start['spawned'].pop(name, None),
                )
            except OSError as exc:
                raise RunStartError(f'{name} could not start: {exc.strerror or exc}') from exc
            continue
        try:
            nodes[name] = classes[name](
                context=ctx, namespace=start['namespace'], **start['params'][name]
            )
        except RunInterrupted:
            raise
        except Exception as exc:
            raise RunStartError(f'{name} could not start: {error_text(exc)}') from exc
        ex.add_node(nodes[name])
    for name, node in nodes.items():
        if isinstance(node, ChildNode):
            why = node.wait_started()
            if why:
                raise RunStartError(f'{name} could not start: {why}')
    src = nodes['frame_source']
    if not src.frames:
        raise RunStartError(_no_frames(src, source))
    # Every node keeps to this study from the start, so another graph's messages are never
    # taken for ours, even when they come first.
    for node in nodes.values():
        node.study.adopt(src.study_id, src.run_id)
    nodes['recorder'].writer.custom_data.update(study_id=src.study_id, run_id=src.run_id)


def _announce(run: _Running, source: dict, mcap, domain_id: int, namespace: str) -> None:
    """Show what runs: frames, phases, the recording, the domain, the live view, the input."""
    src = run.nodes['frame_source']
    where = '' if namespace == '/' else f', namespace {namespace}'
    run.progress(
        f'[mlv-ros] {len(src.frames)} frames, {run.num_phases} phases -> {mcap} '
        f'(ROS_DOMAIN_ID={domain_id}{where}, '
        f'study {src.study_id}, run {src.run_id})'
    )
    if 'live_view' in run.nodes:
        run.progress(
            f'[mlv-ros] live view: {run.nodes["live_view"].url} (Foxglove: Open connection, '
            'Foxglove WebSocket; '
            f'layout config/foxglove_layout.json)'
        )
    if src.not_used or src.left_out or source.get('study'):
        run.progress(
            f'[mlv-ros] {src.dicom_choice}; {len(src.not_used)} series under the folder not used, '
            f'{len(src.left_out)} part(s) of the study left out (see not_used / left_out in '
            'summary.json)'
        )
    run.on_phase(0, run.num_phases)


def _finished(run: _Running) -> bool:
    """Return whether every phase is analysed, or attempted (the input all sent)."""
    from mlv_ros import qos

    src, solver, analyzer = (run.nodes[n] for n in GRAPH_ROLES)
    if not (src.done and run.num_phases):
        return False
    return analyzer.published >= run.num_phases or (
        solver.next_phase >= run.num_phases
        and not analyzer.clouds
        and _taken(analyzer, analyzer.topic_name(qos.MOTION)) >= solver.published
    )  # every phase attempted (some may have failed; diagnostics say which)


def _spin(run: _Running, timeout: float) -> tuple[str | None, str | None]:
    """
    Spin the graph until it is done, a signal comes, or it fails, stalls or times out.

    Returns
    -------
    interrupted : str or None
        The first signal's name.
    failed : str or None
        Why the run failed (a node raised, was stuck, nothing happened, the time ran out).

    """
    nodes, ex = run.nodes, run.ex
    src, solver, analyzer = (nodes[n] for n in GRAPH_ROLES)
    # Longest a healthy graph stays idle: registration and the solver wait this long for input
    # that may still come before acting on what they have (the solver also for its subscribers),
    # and the source, before publishing, for its subscribers.
    waits = [
        getattr(nodes['registration'], 'ed_timeout_s', 5.0),
        getattr(solver, 'incomplete_timeout_s', 5.0),
        getattr(solver, 'wait_timeout_s', 10.0),
    ]
    stall_after = {
        False: 15.0 + max(waits + [getattr(src, 'wait_timeout_s', 30.0)]),
        True: 15.0 + max(waits),
    }
    seen = 0
    activity, active_at = _activity(nodes), time.monotonic()
    while True:
        try:
            ex.spin_once(timeout_sec=0.05)
        except Exception as exc:  # a callback raised: that node is gone
            return None, f'{_raising_node(exc, nodes)} failed: {error_text(exc)}'
        if analyzer.published > seen:
            seen = analyzer.published
            run.phase_analysed(seen)
        if run.signals.received:
            return run.signals.first, None
        failed = _stuck(nodes)
        if failed or _finished(run):
            return None, failed
        now = time.monotonic()
        if _activity(nodes) != activity:
            activity, active_at = _activity(nodes), now
        elif now - active_at > stall_after[src.done]:
            waiting = (
                'after the last frame, the solver still waiting for phase '
                f'{solver.next_phase} of '
                f'{run.num_phases} (is the input cut short?)'
                if src.done
                else 'before the input ended'
            )
            return None, (
                f'nothing happened for {now - active_at:.0f} s {waiting}; {_statuses(nodes)}'
            )
        if now - run.t0 > timeout:
            return None, f'timed out after {timeout:g} s (--timeout); {_statuses(nodes)}'


def _wind_down(run: _Running, interrupted, failed, grace: float) -> None:
    """
    Let the phases in flight finish, then let the recorder take what was sent.

    After a signal: the input stops, and the graph settles for at most ``grace`` seconds (a
    second signal stops waiting). After a failure: the input stops. After a run that ended by
    itself: the last results reach their subscribers. Then only the recorder is spun.
    """
    from mlv_ros.graph_process import ChildNode

    src, rec = run.nodes['frame_source'], run.nodes['recorder']
    if interrupted:
        src.halt(f'{interrupted} received')
        run.progress(
            f'[mlv-ros] {interrupted}: input stopped after {src.published} of '
            f'{len(src.frames)} frames; '
            f'finishing the phases in flight (at most {grace:g} s; {interrupted} again '
            'stops now)'
        )
        _settle(
            run.ex,
            run.nodes,
            lambda: len(run.signals.received) > 1,
            quiet_s=QUIET_S,
            max_s=grace,
            on_phase=run.phase_analysed,
        )
    elif failed:
        src.halt('the run failed')
    else:  # ended by itself: let the last results reach their subscribers (the recorder)
        _settle(
            run.ex,
            run.nodes,
            lambda: bool(run.signals.received) or _all_recorded(run.nodes),
            quiet_s=QUIET_S,
            max_s=grace,
        )
    # Only the recorder from here: it takes what was sent, nothing new is computed (a node in
    # a child process first publishes what it has taken, then ends with its final counts).
    children = [n for n in run.nodes.values() if isinstance(n, ChildNode)]
    # With everything recorded the children end while the recorder drains; else one by one first.
    overlap = not (interrupted or failed) and _all_recorded(run.nodes)
    for node in children:
        if overlap:
            node.request_stop(drain=False)
        else:
            node.stop()
    for name, node in run.nodes.items():
        if name != 'recorder' and node not in children:
            run.ex.remove_node(node)

    def drain():
        _settle(
            run.ex,
            {'recorder': rec},
            lambda: False,
            quiet_s=DRAIN_QUIET_S,
            max_s=DRAIN_MAX_S,
            count=lambda: rec.messages_handled,
        )

    drain()
    if overlap:
        for node in children:
            node.stop()
        if not _all_recorded(run.nodes):  # a child published on its way out
            drain()


def _all_recorded(nodes: dict) -> bool:
    """
    Check whether the recorder has taken every result the graph's nodes published.

    Frames, tag point sets (as many as the detector published and the solver took), the
    registered model, each phase's motion and state, and the metrics; topics it does not record
    are left out. Once they are, a run that ended by itself has nothing in flight to wait for.
    """
    from mlv_ros import qos

    rec, solver = nodes['recorder'], nodes['meshless_solver']
    registered = int(getattr(nodes['registration'], 'result', None) is not None)
    published = {
        qos.FRAMES: nodes['frame_source'].published,
        qos.TAG_POINTS: max(
            nodes['tag_detector'].published, _taken(solver, solver.topic_name(qos.TAG_POINTS))
        ),
        qos.REGISTERED_CLOUD: registered,
        qos.REGISTERED_STATE: registered,
        qos.MOTION: solver.published,
        qos.MODEL_STATE: solver.published,
        qos.METRICS: nodes['motion_analyzer'].published,
    }
    return all(
        _taken(rec, rec.topic_name(topic)) >= count
        for topic, count in published.items()
        if topic in rec.recorded
    )


def _close_recording(run: _Running, mcap, interrupted, failed) -> tuple[bool, str | None]:
    """
    Close the recording with the marks that say how the run ended.

    The bag's metadata (metadata.yaml and the file's rosbag2 record) says how the run ended, so
    the recording alone tells an unfinished run.

    Returns
    -------
    complete : bool
        Every phase analysed, not interrupted, nothing failed.
    failed : str or None
        Why the run failed (``failed``, or the recorder's own failure).

    """
    from mlv_ros import bagio

    rec, analyzer = run.nodes['recorder'], run.nodes['motion_analyzer']

    def outcome():
        why = failed or (f'recorder: {rec.failure}' if rec.failure else None)
        done = (
            not interrupted
            and not why
            and bool(run.num_phases)
            and analyzer.published >= run.num_phases
        )
        marks = {
            'complete': str(done).lower(),
            **({'interrupted': interrupted} if interrupted else {}),
            **({'failed': why} if why else {}),
        }
        return done, why, marks

    was_closed = rec.writer.closed  # by a write error, before the marks
    rec.writer.custom_data.update(outcome()[2])
    rec.finish()
    complete, failed, marks = outcome()
    if was_closed or marks != {k: rec.writer.custom_data.get(k) for k in marks}:
        rec.writer.custom_data.update(marks)
        try:
            bagio.write_bag_metadata(mcap, rec.writer)
        except OSError:
            pass  # a full disk: the recorder reported it, the summary says so
    return complete, failed


def _run_summary(run: _Running, source: dict, out_dir, mcap, domain_id, namespace, ended) -> dict:
    """
    Return the run's summary (see :func:`run_graph`).

    Parameters
    ----------
    run : _Running
        The graph, after :func:`_close_recording`.
    source, out_dir, namespace
        As :func:`run_graph`'s.
    mcap : Path
        The recording.
    domain_id : int
        The domain the run talked on.
    ended : dict
        ``complete``, ``interrupted`` and ``failed``: how the run ended.

    Returns
    -------
    dict
        The summary written to ``summary.json``.

    """
    from mlv_ros.nodes.common import status_text

    nodes = run.nodes
    src, solver, analyzer = (nodes[n] for n in GRAPH_ROLES)
    rec = nodes['recorder']
    summary = {
        'source': source,
        'run_dir': str(out_dir),
        'mcap': str(mcap),
        'ros_domain_id': domain_id,
        'namespace': namespace,
        'study_id': src.study_id,
        'run_id': src.run_id,
        'seconds': round(time.monotonic() - run.t0, 2),
        'frames_published': src.published,
        'tag_sets_published': nodes['tag_detector'].published,
        'phases_solved': solver.published,
        'metrics_published': analyzer.published,
        'num_phases': run.num_phases,
        'recorded_messages': rec.writer.message_count,
        'diagnostics_sent': sum(n.diagnostics_sent for n in nodes.values()),
        'complete': ended['complete'] and src.input_complete,
        'interrupted': ended['interrupted'],
        'failed': ended['failed'],
        'phases_complete': ended['complete'],
        **verdict_summary(analyzer.verdicts),
        'cavity_volume_ml': {str(p): round(v, 2) for p, v in sorted(analyzer.volumes.items())},
        'registration_verdict': registration_summary(nodes['registration']),
        'segment_origin': segment_origin_summary(nodes['registration']),
        **twist_summary(solver, analyzer),
        # the latest ERROR of each node that had one: why an incomplete run is incomplete
        'last_errors': {
            name: status_text(n.last_error)
            for name, n in nodes.items()
            if n.last_error is not None
        },
    }
    if source.get('source') == 'dicom':
        # What of the input was used: the study taken and why, what of it was left out (then
        # the run is not complete), and every series under the folder not used, with why.
        summary['input_complete'] = src.input_complete
        summary['dicom_study'] = src.dicom_choice
        summary['left_out'] = [f'{path}: {why}' for path, why in src.left_out]
        summary['not_used'] = [f'{path}: {why}' for path, why in src.not_used]
    other = {name: sum(n.other_studies.values()) for name, n in nodes.items() if n.other_studies}
    if other:  # another graph on the domain: its messages were reported and left out
        summary['messages_of_other_studies'] = other
    if rec.other_graph_statuses:  # /diagnostics of other graphs' nodes, left out of the recording
        summary['statuses_of_other_graphs'] = rec.other_graph_statuses
    if 'live_view' in nodes:
        view = nodes['live_view']
        summary['live_view'] = {
            'url': view.url,
            'phases_shown': view.clouds_served,
            'phases_not_shown': {str(p): why for p, why in sorted(view.phases_not_shown.items())},
        }
    if rec.writer.error is not None:
        summary['recording_error'] = str(rec.writer.error)
        summary['messages_not_recorded'] = rec.dropped
    return summary


def _run_graph(
    source,
    out_dir,
    params_file,
    overrides,
    timeout,
    progress,
    domain_id,
    grace,
    signals,
    namespace,
    live=None,
    on_phase=lambda done, total: None,
    spawned=None,
) -> dict:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    mcap = out_dir / 'run.mcap'
    names, namespace, params_path, params, overrides = _graph_parameters(
        source, mcap, params_file, overrides, namespace, live
    )
    separate = child_nodes()
    classes = {name: node_class(name) for name in names if name not in separate}
    domain_id = _claimed_domain(domain_id, namespace)
    created = _prepare_out(out_dir)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    t0 = time.monotonic()
    nodes = {}
    start = {
        'domain_id': domain_id,
        'namespace': namespace,
        'params_path': params_path,
        'params': params,
        'overrides': overrides,
        'spawned': {} if spawned is None else spawned,
    }
    try:
        ex = SingleThreadedExecutor(context=ctx)
        _start_nodes(ex, ctx, nodes, names, classes, start, source)
        signals.starting = False
    except (RunStartError, RunInterrupted):
        # Nothing was spun, so nothing was recorded: leave no empty run behind to block --out.
        signals.starting = False
        if 'recorder' in nodes:
            nodes['recorder'].writer.discard()
        mcap.unlink(missing_ok=True)  # a signal may have come before the recorder was in `nodes`
        _remove_dirs(created)
        for node in nodes.values():
            node.destroy_node()
        ctx.try_shutdown()
        raise
    num_phases = max((f.num_phases for f in nodes['frame_source'].frames), default=0)
    run = _Running(ex, nodes, num_phases, t0, progress, on_phase, signals)
    _announce(run, source, mcap, domain_id, namespace)
    try:
        interrupted, failed = _spin(run, timeout)
        _wind_down(run, interrupted, failed, grace)
        complete, failed = _close_recording(run, mcap, interrupted, failed)
        ended = {'complete': complete, 'interrupted': interrupted, 'failed': failed}
        summary = _run_summary(run, source, out_dir, mcap, domain_id, namespace, ended)
    finally:
        for node in nodes.values():
            node.destroy_node()
        ctx.try_shutdown()
    write_summary(out_dir, summary)
    return summary


def _settle(
    ex, nodes: dict, stop, quiet_s: float, max_s: float, count=None, on_phase=None
) -> None:
    """
    Spin until nothing has happened for ``quiet_s``, ``max_s`` have passed, or ``stop()``.

    A callback that computes for long (a phase being solved) blocks ``spin_once``, and what it
    publishes counts as activity as soon as it returns, so a phase in flight is waited for.
    """
    count = count or (lambda: _activity(nodes))
    analyzer = nodes.get('motion_analyzer')
    seen = analyzer.published if analyzer is not None else 0
    last, last_at = count(), time.monotonic()
    end = time.monotonic() + max_s
    while time.monotonic() < end and time.monotonic() - last_at < quiet_s and not stop():
        try:
            ex.spin_once(timeout_sec=0.05)
        except Exception:
            return  # a node failing while the run ends: keep what there is
        if count() != last:
            last, last_at = count(), time.monotonic()
        if analyzer is not None and on_phase and analyzer.published > seen:
            seen = analyzer.published
            on_phase(seen)


def verdict_summary(verdicts: dict) -> dict:
    """
    Return ``phases_ok`` and the degraded / failed phases with their reasons.

    ``phases_ok`` and the ``degraded`` / ``failed`` phases (:mod:`mlv_ros.core.verdict`) come from
    the analyzer's phase → (level, reasons).
    """
    out = {'phases_ok': sorted(p for p, (v, _) in verdicts.items() if v == 0)}
    for level, name in ((1, 'phases_degraded'), (2, 'phases_failed')):
        out[name] = {str(p): why for p, (v, why) in sorted(verdicts.items()) if v == level}
    return out


def twist_summary(solver, analyzer) -> dict:
    """
    Return the run summary's twist fields: the measured levels and what is extrapolated.

    ``twist_measured_levels`` (the levels, 0 apex … 1 base, that SA slices with tag points cross;
    None without any) and ``twist_extrapolated`` (what of the twist and torsion is extrapolated,
    one sentence; '' when nothing is), once the solver has taken its ED phase.
    """
    from mlv_ros.core.analysis.frame import twist_extrapolation_note

    if getattr(solver, 'frame', None) is None or solver.next_phase == 0:
        return {}
    span = solver.twist_span
    return {
        'twist_measured_levels': None if span is None else [round(span[0], 3), round(span[1], 3)],
        'twist_extrapolated': twist_extrapolation_note(
            span, analyzer.levels, getattr(solver, 'twist_gradient_se', None)
        ),
    }


def registration_summary(node) -> dict | None:
    """Return the ED registration's verdict and reasons (None before it registered)."""
    v = getattr(node, 'verdict', None)
    return None if v is None else {'verdict': v.name, 'reasons': v.text}


def segment_origin_summary(node) -> dict | None:
    """
    Return where the AHA segments' circumferential origin came from.

    None before it registered; else ``source`` detected (the RV in the ED SA images) / prior (not
    tied to the anatomy) / given, the insertion directions and confidence
    (:meth:`SeptumEstimate.to_dict`).
    """
    res = getattr(node, 'result', None)
    septum = getattr(res, 'septum', None)
    return None if septum is None else septum.to_dict()


def verdict_line(summary: dict) -> str | None:
    """Which phases are not to be taken at face value, in one line (None when all are ok)."""
    bad = [
        (name, sorted(int(p) for p in summary.get(key) or {}))
        for name, key in (('degraded', 'phases_degraded'), ('failed', 'phases_failed'))
    ]
    if not any(phases for _, phases in bad):
        return None
    parts = [
        f'{len(phases)} {name} ({", ".join(map(str, phases))})' for name, phases in bad if phases
    ]
    return (
        f'of {summary["num_phases"]} phases, {" and ".join(parts)}: see phases_degraded / '
        'phases_failed in '
        f'summary.json for why; a failed phase is not a measurement'
    )


def untracked(summary: dict) -> bool:
    """Check whether the study could not be tracked (every analysed phase after ED failed)."""
    after_ed = [p for p in summary.get('phases_ok', []) if int(p) > 0]
    after_ed += [
        p
        for key in ('phases_degraded', 'phases_failed')
        for p in summary.get(key) or {}
        if int(p) > 0
    ]
    failed = [p for p in summary.get('phases_failed') or {} if int(p) > 0]
    return bool(after_ed) and len(failed) == len(after_ed)


def write_summary(out_dir: Path, summary: dict) -> None:
    """
    Write ``summary.json`` in the run directory, whole or not at all.

    It is written beside, then renamed (a full disk left an empty file); on a write error the
    summary says so instead (``summary_error``) and an earlier summary.json stays as it was.
    """
    path = Path(out_dir) / 'summary.json'
    part = path.with_name('.summary.json.part')
    try:
        part.write_text(json.dumps(summary, indent=2))
        os.replace(part, path)
    except OSError as exc:
        part.unlink(missing_ok=True)
        summary['summary_error'] = f'summary.json not written: {exc.strerror or exc}'


def params_error(path: Path) -> str | None:
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        return f'--params {path}: {exc.strerror or exc}'
    except yaml.YAMLError as exc:
        return f'--params {path} is not valid YAML: {str(exc).splitlines()[0]}'
    if data is not None and not (isinstance(data, dict) and _params_shape(data)):
        return (
            f'--params {path}: want /**/node: {{ros__parameters: {{name: value}}}} '
            '(a ROS parameters file, as config/graph.yaml)'
        )
    return None


def _params_shape(data: dict) -> bool:
    """
    Check whether ``data`` is shaped as a ROS parameters file.

    That is, node (or namespace) keys down to ``ros__parameters`` maps.
    """
    return all(
        isinstance(value, dict) or value is None
        if key == 'ros__parameters'
        else isinstance(value, dict) and _params_shape(value)
        for key, value in data.items()
    )


def exit_status(summary: dict) -> tuple[int, str]:
    """Return what ``mlv-ros run`` exits with for ``summary``, and in a few words why."""
    if summary['interrupted']:
        return SIGNAL_EXIT[
            signal.Signals[summary['interrupted']]
        ], f'interrupted by {summary["interrupted"]}'
    if summary['phases_complete'] and untracked(summary):
        return EXIT_UNTRACKED, 'the study could not be tracked'
    if summary['complete']:
        return 0, 'complete'
    return EXIT_INCOMPLETE, 'not complete (why: the line below)'


def outcome_line(summary: dict) -> str | None:
    """How a run that did not complete ended, in one line (None for a complete run)."""
    kept = (
        f'{summary["phases_solved"]} of {summary["num_phases"]} phases solved, '
        f'{summary["metrics_published"]} analysed; {summary["recorded_messages"]} messages in '
        f'{summary["mcap"]}'
    )
    if summary.get('recording_error') and not str(summary.get('failed')).startswith('recorder:'):
        kept += f' (recording stopped: {summary["recording_error"]})'
    if summary.get('summary_error'):
        kept += f' ({summary["summary_error"]})'
    if summary['interrupted']:
        return f'interrupted by {summary["interrupted"]}: {kept}, marked incomplete'
    if summary['failed']:
        return f'{summary["failed"]}. Kept: {kept}'
    if summary.get('phases_complete') and summary.get('input_complete') is False:
        left = summary.get('left_out') or []
        return (
            f'incomplete input: every phase analysed, but {len(left)} part(s) of the study '
            'were left out '
            f'(first: {left[0] if left else "?"}): see left_out in summary.json, and complete '
            'the folder'
        )
    if not summary['complete']:
        errors = summary.get('last_errors') or {}
        why = '; '.join(f'{name}: {text}' for name, text in errors.items())
        return f'incomplete: {kept}' + (f' (last errors: {why})' if why else '')
    return None
