"""Soak and fault suite of the ``facade_mapper`` node (issue 13): ``make soak``.

Starts the node in its own process (the default parameter file, ``config/facade_mapper.yaml``,
unless ``--params`` says otherwise), acts as the rest of the robot from this process
(rclpy) and runs three sections, each writing its part of the report:

``soak``
    publishes PointCloud2 clouds cut from the simulated street drive (``--points`` points
    each, ``--rate`` per second, for ``--minutes``; after the first lap of the drive every
    lap is the drive again with 1 cm of fresh noise), calls ``query_points`` all along
    (``--query-period``) and every ``--sample-period`` seconds samples the node's memory
    (VmRSS of /proc/PID/status, summed over the node and its mapping process), its queue
    and its ``/diagnostics`` counters, and the query latencies (p50/p95). At the end every cloud must be accounted for: published =
    received by the node, and received = mapped + dropped + rejected + failed + waiting
    (points: + not_building + nonfinite).
``kills``
    ``--kills`` times: changes the map, asks for ``save_map`` and SIGKILLs the node while the
    file is written (once a random share of it is in the hidden ``.NAME.*.tmp`` file the
    save writes first; the first kill at half of it, some after the rename), restarts the
    node on the saved file and checks that the file is
    whole (loads, and is the old or the new map), that no temporary file is left after the
    restart and that the restarted node answers ``query_points`` exactly as the file
    queried offline does.
``fuzz``
    :func:`fuzz_cases`: malformed clouds, bad service requests and bad sensor poses. After
    each, the node must be alive, answer a query, and (unless the input was valid) have the
    same map: the same answers to a fixed set of query points and the same map version.
    A dead node is restarted and a changed map reloaded from the baseline file, so that every
    case starts from the same map.

Everything lands in ``--out`` (default ``output/soak``): ``report.json``, ``report.txt``
(the tables), ``soak.png`` (memory, map points, queue, update latency and query latency over
time), the node logs and the map files.

The node's counters: the keys ``clouds_received``, ``clouds_mapped``, ``clouds_dropped``,
``clouds_rejected``, ``clouds_failed``, ``clouds_waiting`` (and ``points_*`` likewise, plus
``points_not_building`` and ``points_nonfinite``), ``poses_rejected``,
``clouds_missed_estimate``, ``latency_seconds`` and ``last_update_seconds`` are used when the
node publishes them; older nodes' ``clouds_in``, ``points_in``, ``clouds_queued`` and
``points_pending`` stand in for missing ones (the report says which keys were missing).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import dataclasses
import hashlib
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from array import array
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .ros_client import ANSWER_KEYS, SpinningClient, answers_of, query_request

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_PARAMS = ROOT / 'config' / 'facade_mapper.yaml'
#: Fast DDS transports for large clouds: without it a fresh node lost every cloud above
#: ~116 KB published to it once (see the file).
DEFAULT_DDS_PROFILE = ROOT / 'config' / 'fastdds_large_clouds.xml'
SECTIONS = ('soak', 'kills', 'fuzz')

#: Share of the published clouds the node's estimate of lost clouds may miss (plus 10).
ESTIMATE_TOLERANCE = 0.01

#: The point fields of the published clouds (float32 coordinates, as drivers send them).
CLOUD_DTYPE = np.dtype([('x', 'f4'), ('y', 'f4'), ('z', 'f4'), ('origin_x', 'f4'), ('origin_y', 'f4'),
                        ('origin_z', 'f4'), ('building_id', 'i4'), ('class', 'u1')])
#: Counters whose change shows that the node took an input in (new keys and today's).
INPUT_COUNTERS = ('clouds_received', 'clouds_in', 'clouds_rejected', 'clouds_dropped', 'clouds_failed',
                  'clouds_mapped', 'points_nonfinite', 'points_not_building', 'poses_rejected')
#: Stand-ins of older nodes for the issue-13 keys.
FALLBACK_KEYS = {'clouds_received': 'clouds_in', 'points_received': 'points_in',
                 'clouds_waiting': 'clouds_queued', 'points_waiting': 'points_pending'}
CLOUD_PARTS = ('mapped', 'dropped', 'rejected', 'failed', 'waiting')
POINT_PARTS = ('mapped', 'not_building', 'nonfinite', 'dropped', 'rejected', 'failed', 'waiting')


# ------------------------------------------------------------------------------------------
# Options
# ------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Options:
    """Settings of a run (the command line's options)."""

    rate: float = 10.0
    points: int = 100_000
    minutes: float = 10.0
    kills: int = 20
    out: Path = Path('output/soak')
    params: Path = DEFAULT_PARAMS
    overrides: tuple[str, ...] = ()
    sample_period: float = 10.0
    query_points: int = 1000
    query_period: float = 1.0
    drive_seconds: float = 0.0
    sections: tuple[str, ...] = SECTIONS
    cases: tuple[str, ...] = ()
    seed: int = 0
    domain: int | None = None
    drain_timeout: float = 300.0
    case_timeout: float = 3.0
    settle_timeout: float = 180.0
    start_timeout: float = 120.0
    huge_query: int = 0
    fuzz_map_points: int = 300_000
    quiet: bool = False
    dds_profile: Path | None = DEFAULT_DDS_PROFILE


#: The quick version (the pytest test in test/node/test_soak.py, ``--quick``): about a minute.
#: Faster diagnostics and idle flush let each fuzz case end sooner; everything else is the
#: parameter file's.
QUICK: dict[str, Any] = {'rate': 2.0, 'points': 4000, 'minutes': 0.15, 'kills': 1, 'sample_period': 4.0, 'query_points': 300,
         'query_period': 0.5, 'drive_seconds': 5.0, 'drain_timeout': 60.0, 'case_timeout': 2.0,
         'settle_timeout': 60.0, 'overrides': ('publish.diagnostics_period:=0.2', 'node.idle_flush:=0.5')}
#: The fuzz cases of the quick version: some of every kind (``make soak`` runs all of them).
QUICK_CASES = (
    'point_step_short', 'row_step_short', 'data_truncated_half', 'missing_x', 'duplicate_x', 'x_datatype_9',
    'x_as_int32', 'x_count_three', 'class_as_float32', 'class_renamed', 'nan_all', 'coords_1e30',
    'coords_f64_1e300', 'origins_1e30', 'bigendian_flag_le_data', 'bigendian_correct', 'huge_width_little_data',
    'huge_width_height', 'empty_cloud', 'frame_unknown',
    'pose_zero_quaternion', 'pose_non_unit_quaternion', 'pose_nan_translation', 'pose_huge_translation', 'pose_valid',
    'query_nan_x', 'query_resolution_negative', 'query_resolution_nan', 'query_empty',
    'save_missing_folder', 'save_sys', 'save_onto_directory',
    'save_absolute_outside', 'save_dotdot', 'save_symlink_out', 'save_over_text_file',
    'load_missing', 'load_truncated_half', 'load_random_bytes', 'load_wrong_version',
    'load_dotdot', 'load_symlink_out', 'load_oversized', 'load_manifest_escaping',
    'get_map_wide_200m')
QUICK['cases'] = QUICK_CASES


def quick_options(out: Path, **changes: Any) -> Options:
    """The quick version's options, writing to ``out``."""
    return dataclasses.replace(Options(), **{**QUICK, 'out': Path(out), **changes})


def parse_args(argv: list[str] | None = None) -> Options:
    """Options from the command line."""
    d = Options()
    p = argparse.ArgumentParser(prog='python -m uncertain_facade_map_apps.soak', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument('--rate', type=float, default=d.rate, help='clouds published per second')
    p.add_argument('--points', type=int, default=d.points, help='points per cloud')
    p.add_argument('--minutes', type=float, default=d.minutes, help='minutes of publishing (soak section)')
    p.add_argument('--kills', type=int, default=d.kills, help='SIGKILLs during save_map (kills section)')
    p.add_argument('--out', type=Path, default=d.out, help='output folder')
    p.add_argument('--params', type=Path, default=d.params, help="the node's parameter file")
    p.add_argument('-p', '--param', dest='overrides', action='append', default=[], metavar='NAME:=VALUE',
                   help='a parameter override for every node start (repeatable)')
    p.add_argument('--sample-period', type=float, default=d.sample_period, help='seconds between samples')
    p.add_argument('--query-points', type=int, default=d.query_points, help='points per latency query')
    p.add_argument('--query-period', type=float, default=d.query_period, help='seconds between latency queries')
    p.add_argument('--drive-seconds', type=float, default=d.drive_seconds,
                   help='seconds of the street drive simulated (0: all of it)')
    p.add_argument('--sections', default=','.join(d.sections), help=f'comma-separated, of {", ".join(SECTIONS)}')
    p.add_argument('--cases', default='', help='comma-separated fuzz case names (default: all; --list-cases)')
    p.add_argument('--list-cases', action='store_true', help='print the fuzz cases and exit')
    p.add_argument('--seed', type=int, default=d.seed, help='seed of the kill moments and the noise')
    p.add_argument('--domain', type=int, default=None, help='ROS_DOMAIN_ID (default: 200 + pid %% 32)')
    p.add_argument('--drain-timeout', type=float, default=d.drain_timeout,
                   help='seconds to wait for the queue to empty after publishing')
    p.add_argument('--case-timeout', type=float, default=d.case_timeout,
                   help='seconds a fuzz cloud or pose may take to show in the counters')
    p.add_argument('--huge-query', type=int, default=0,
                   help='points of the over-limit query (0: service.max_query_points + 1)')
    p.add_argument('--fuzz-map-points', type=int, default=d.fuzz_map_points,
                   help='the fuzz cases run on a fresh node fed the start of the drive when the map is larger')
    p.add_argument('--dds-profile', default=str(d.dds_profile),
                   help='Fast DDS XML profile for the node and the clients (FASTRTPS_DEFAULT_PROFILES_FILE; '
                        '"none": Fast DDS\'s defaults, with which large clouds sent once are lost)')
    p.add_argument('--quick', action='store_true', help='the quick version (about a minute)')
    p.add_argument('--quiet', action='store_true', help='no progress lines')
    a = p.parse_args(argv)
    if a.list_cases:
        for case in fuzz_cases():
            print(f'{case.name:32s} {case.group:8s} {"valid" if case.valid else "bad"}  {case.about}')
        raise SystemExit(0)
    sections = tuple(s.strip() for s in a.sections.split(',') if s.strip())
    if set(sections) - set(SECTIONS):
        p.error(f'unknown section in --sections {a.sections!r}')
    values = {k: getattr(a, k) for k in ('rate', 'points', 'minutes', 'kills', 'out', 'params', 'sample_period',
                                         'query_points', 'query_period', 'drive_seconds', 'seed', 'domain',
                                         'drain_timeout', 'case_timeout', 'huge_query', 'fuzz_map_points',
                                         'quiet')}
    values['sections'] = sections
    values['cases'] = tuple(c.strip() for c in a.cases.split(',') if c.strip())
    values['overrides'] = tuple(a.overrides)
    values['dds_profile'] = None if a.dds_profile.lower() == 'none' else Path(a.dds_profile)
    if a.quick:
        explicit = {k for k in values if f'--{k.replace("_", "-")}' in (argv if argv is not None else sys.argv)}
        values.update({k: v for k, v in QUICK.items() if k not in explicit})
        values['overrides'] = QUICK['overrides'] + tuple(a.overrides)
        if a.cases:
            values['cases'] = tuple(c.strip() for c in a.cases.split(',') if c.strip())
    return Options(**values)


def say(opts: Options, text: str) -> None:
    if not opts.quiet:
        print(f'[soak {time.strftime("%H:%M:%S")}] {text}', flush=True)


# ------------------------------------------------------------------------------------------
# The drive: clouds and query points
# ------------------------------------------------------------------------------------------
def simulate_drive(seconds: float = 0.0) -> np.ndarray:
    """The simulated street drive (campaign 0), time-ordered, as :data:`CLOUD_DTYPE` points."""
    from uncertain_facade_map.simulation.campaign import simulate_campaign
    from uncertain_facade_map.simulation.scenes import build_scene

    window = (0.0, seconds) if seconds > 0 else None
    cloud = simulate_campaign(build_scene('street', 0), 0, window=window)
    out = np.zeros(len(cloud.points), CLOUD_DTYPE)
    for name in CLOUD_DTYPE.names:
        out[name] = cloud.points[name]
    return out


def cut_cloud(drive: np.ndarray, index: int, size: int, seed: int = 0) -> np.ndarray:
    """Cloud ``index`` of ``size`` points: the drive cut in consecutive pieces, round and round;
    every lap after the first gets 1 cm of fresh Gaussian noise (the street seen again)."""
    start = index * size
    idx = np.arange(start, start + size) % len(drive)
    points = drive[idx]
    lap = start // len(drive)
    if lap > 0 or (start + size) > len(drive):
        rng = np.random.default_rng([seed, index])
        laps = np.arange(start, start + size) // len(drive)
        noisy = laps > 0
        for name in ('x', 'y', 'z'):
            points[name][noisy] += rng.normal(0.0, 0.01, int(noisy.sum())).astype(np.float32)
    return points


def probe_points(drive: np.ndarray, n: int, seed: int = 0, share: float = 1.0) -> np.ndarray:
    """(n, 3) query points: building points of the drive's first ``share``, 0.3 m of noise."""
    rng = np.random.default_rng(seed)
    part = drive[:max(1, int(len(drive) * share))]
    building = part[part['class'] == 1]
    xyz = np.stack([building['x'], building['y'], building['z']], 1).astype(np.float64)
    return xyz[rng.choice(len(xyz), n, replace=len(xyz) < n)] + rng.normal(0.0, 0.3, (n, 3))


def cloud_message(points: np.ndarray, stamp_ns: int, frame: str = 'map') -> Any:
    import msg_adapters as ma

    return ma.pointcloud2_from_structured(points, stamp_ns=stamp_ns, frame_id=frame, msg_types=ma.rclpy_types())


# ------------------------------------------------------------------------------------------
# The node's process
# ------------------------------------------------------------------------------------------
def _children(pid: int) -> list[int]:
    """The process ids of ``pid``'s children (from /proc/PID/task/*/children)."""
    out: list[int] = []
    for task in Path(f'/proc/{pid}/task').glob('*'):
        try:
            out.extend(int(c) for c in (task / 'children').read_text().split())
        except (OSError, ValueError):
            continue
    return out


class NodeDied(RuntimeError):
    """The node's process ended (or never came up)."""


class NodeProcess:
    """The node, started as ``python -m uncertain_facade_map_node.node --ros-args --params-file P -p ...``."""

    def __init__(self, params: Path, overrides: list[str], log: Path, env: dict) -> None:
        self.log = log
        self.started = time.monotonic()
        cmd = [sys.executable, '-m', 'uncertain_facade_map_node.node', '--ros-args', '--params-file', str(params)]
        for item in overrides:
            cmd += ['-p', item]
        self.cmd = cmd
        self._log_file = open(log, 'ab')
        self.proc = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=self._log_file, stderr=subprocess.STDOUT)
        self.pid = self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def memory_by_process(self) -> dict[int, tuple[int, int]]:
        """(VmRSS, VmHWM) in kB from /proc/PID/status of the node and of each of its child
        processes (the mapping process, the published maps' helper), by pid; empty once the
        node is gone."""
        out: dict[int, tuple[int, int]] = {}
        for pid in [self.pid, *_children(self.pid)]:
            try:
                text = Path(f'/proc/{pid}/status').read_text()
            except OSError:
                continue
            found = dict(re.findall(r'^(VmRSS|VmHWM):\s+(\d+)', text, re.M))
            out[pid] = (int(found.get('VmRSS', 0)), int(found.get('VmHWM', 0)))
        return out if self.pid in out else {}

    def log_size(self) -> int:
        try:
            return self.log.stat().st_size
        except OSError:
            return 0

    def log_since(self, offset: int) -> str:
        with open(self.log, 'rb') as fh:
            fh.seek(offset)
            return fh.read().decode('utf-8', 'replace')

    def kill(self) -> None:
        if self.alive():
            self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(30)
        self._log_file.close()

    def stop(self) -> None:
        if self.alive():
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.kill()
        self._log_file.close()


def exception_text(log: str) -> str:
    """The last exception line of a traceback in ``log``, else its last error line, else ''."""
    lines = [line.strip() for line in log.splitlines() if line.strip()]
    if 'Traceback' in log:
        after = log[log.rindex('Traceback'):].splitlines()
        for line in reversed(after):
            if re.match(r'^[\w.]+(Error|Exception|Exit|Interrupt)\b', line.strip()):
                return line.strip()[:300]
    for line in reversed(lines):
        if ('[ERROR]' in line or '[FATAL]' in line or line.startswith('facade_mapper: ')
                or 'Segmentation' in line or 'Killed' in line):
            return line[:300]
    return ''


# ------------------------------------------------------------------------------------------
# This process's ROS side
# ------------------------------------------------------------------------------------------
class Client(SpinningClient):
    """Publishes clouds and poses, listens to /diagnostics, calls the node's services."""

    def __init__(self, domain: int) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import TransformStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        super().__init__('soak_client', domain, num_threads=3)
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.node.create_publisher(PointCloud2, 'points', reliable)
        self.pose_pub = self.node.create_publisher(TransformStamped, 'sensor_pose', 100)
        self._diag = threading.Condition()
        self.diag_values: dict[str, str] = {}
        self.diag_time = 0.0
        self.diag_count = 0
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)
        self.clients: dict[str, Any] = {}
        self._clients_lock = threading.Lock()
        #: Whether the server still runs: a call gives up as soon as it does not.
        self.server_alive: Callable[[], bool] = lambda: True
        self._start()

    def _on_diagnostics(self, msg: Any) -> None:
        from uncertain_facade_map.params import NODE_NAME

        status = [s for s in msg.status if s.hardware_id == NODE_NAME] or list(msg.status)
        if not status:
            return
        with self._diag:
            self.diag_values = {kv.key: kv.value for kv in status[0].values}
            self.diag_time = time.monotonic()
            self.diag_count += 1
            self._diag.notify_all()

    def diagnostics(self, after: float = 0.0, until: Callable[[dict], bool] | None = None,
                    timeout: float = 30.0) -> dict | None:
        """The first diagnostics received after ``after`` (monotonic) for which ``until`` holds; None on timeout."""
        deadline = time.monotonic() + timeout
        with self._diag:
            while True:
                if self.diag_time > after and (until is None or until(self.diag_values)):
                    return dict(self.diag_values)
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._diag.wait(min(left, 0.5))

    def _client(self, srv_type: Any, name: str) -> Any:
        with self._clients_lock:
            if name not in self.clients:
                self.clients[name] = self.on_spin_thread(lambda: self.node.create_client(srv_type, name))
            return self.clients[name]

    def call(self, srv_type: Any, name: str, request: Any, timeout: float = 60.0) -> Any:
        """The response, or None when the service is not there or does not answer in time."""
        client = self._client(srv_type, name)
        if not client.wait_for_service(timeout_sec=min(timeout, 10.0)):
            return None
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        deadline = time.monotonic() + timeout
        while not done.wait(0.2):
            if time.monotonic() > deadline or not self.server_alive():
                with contextlib.suppress(Exception):
                    client.remove_pending_request(future)
                return None
        return future.result()

    def points_subscribers(self) -> set[tuple[int, ...]]:
        """The endpoint ids of the subscriptions to ``points`` in the ROS graph (a killed node's
        stay there until its lease ends, so a count would take them for the new node's)."""
        def info() -> set[tuple[int, ...]]:
            return {tuple(e.endpoint_gid) for e in self.node.get_subscriptions_info_by_topic(self.pub.topic_name)}
        return self.on_spin_thread(info)

    def forget_clients(self) -> None:
        """Drop the service clients (the node was restarted)."""
        with self._clients_lock:
            clients, self.clients = list(self.clients.values()), {}
        self.on_spin_thread(lambda: [self.node.destroy_client(c) for c in clients])


def same_answers(a: dict | None, b: dict | None) -> bool:
    """Equal bit for bit, NaN equal to NaN."""
    if a is None or b is None:
        return False
    return all(np.array_equal(np.asarray(a[k]), np.asarray(b[k]), equal_nan=np.asarray(a[k]).dtype.kind == 'f')
               for k in ANSWER_KEYS)


def version_of(message: str) -> int | None:
    found = re.search(r'map version (\d+)', message or '')
    return int(found.group(1)) if found else None


def offline_answers(path: Path, xyz: np.ndarray, resolution: float = 0.1) -> dict[str, np.ndarray]:
    """What the map file answers offline (the core's query with the map's own bands and the
    node's default ``query.*`` settings)."""
    from uncertain_facade_map.io.map_file import load_map
    from uncertain_facade_map.params import QueryConfig

    fmap = load_map(path)
    return fmap.query(xyz, QueryConfig(), resolution).as_dict()


def as_int(values: dict | None, key: str) -> int | None:
    if not values or key not in values:
        return None
    try:
        return int(float(values[key]))
    except ValueError:
        return None


def as_float(values: dict | None, key: str) -> float | None:
    if not values or key not in values:
        return None
    try:
        return float(values[key])
    except ValueError:
        return None


def counter(values: dict, key: str) -> tuple[int | None, str | None]:
    """A counter and the key it came from (an older node's stand-in when the key is missing)."""
    if key in values:
        return as_int(values, key), key
    other = FALLBACK_KEYS.get(key)
    if other and other in values:
        return as_int(values, other), other
    return None, None


def settled(values: dict) -> bool:
    """Nothing waits: no cloud queued or in work, no point held back, the map fitted whole."""
    waiting, _ = counter(values, 'clouds_waiting')
    return values.get('settled', 'True') == 'True' and not waiting and not as_int(values, 'points_pending')


# ------------------------------------------------------------------------------------------
# The session: one client, the node's process and its restarts
# ------------------------------------------------------------------------------------------
class Session:
    """What the sections share: options, the client, the node, the drive and its probe points."""

    def __init__(self, opts: Options) -> None:
        self.opts = opts
        self.out = Path(opts.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.domain = opts.domain if opts.domain is not None else 200 + os.getpid() % 32
        self.env = dict(os.environ, ROS_DOMAIN_ID=str(self.domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
        if opts.dds_profile is not None:
            if not Path(opts.dds_profile).is_file():
                raise FileNotFoundError(f'the Fast DDS profile {opts.dds_profile} does not exist')
            # For the node (env) and for this process's clients and the query process (os.environ,
            # read when their participants are created).
            self.env['FASTRTPS_DEFAULT_PROFILES_FILE'] = os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = \
                str(Path(opts.dds_profile).resolve())
        self.client: Client | None = None
        self.node: NodeProcess | None = None
        self.starts = 0
        self.drive = np.zeros(0, CLOUD_DTYPE)
        self.probe = np.zeros((0, 3))
        self.next_cloud = 0
        self.rng = np.random.default_rng(opts.seed)
        self.start_seconds: list[float] = []
        self.max_query_points = _param_value(opts, 'service.max_query_points', 1_000_000)

    def open(self) -> None:
        self.client = Client(self.domain)
        self.client.server_alive = self.alive
        t = time.monotonic()
        self.drive = simulate_drive(self.opts.drive_seconds)
        self.probe = probe_points(self.drive, 500, self.opts.seed, share=0.5)
        say(self.opts, f'simulated {len(self.drive):,} points of the street drive in {time.monotonic() - t:.1f} s')

    def close(self) -> None:
        if self.node is not None:
            self.node.stop()
        if self.client is not None:
            self.client.close()

    def start_node(self, map_path: Path | None = None, tag: str = 'node') -> NodeProcess:
        """Start the node (on ``map_path`` when given) and wait until it is up; raises NodeDied."""
        if self.node is not None and self.node.alive():
            self.node.stop()
        # The node's map folder (save_map and load_map are confined to it): this run's folder.
        overrides = [f'persistence.map_dir:={self.out.resolve()}', *self.opts.overrides]
        if map_path is not None:
            overrides.append(f'persistence.map_path:={map_path}')
        self.starts += 1
        log = self.out / 'logs' / f'{self.starts:03d}_{tag}.log'
        log.parent.mkdir(parents=True, exist_ok=True)
        t = time.monotonic()
        known = self.client.points_subscribers() if self.client is not None else set()
        self.node = NodeProcess(Path(self.opts.params), overrides, log, self.env)
        self.wait_ready(self.node, known)
        self.start_seconds.append(time.monotonic() - t)
        return self.node

    def wait_ready(self, node: NodeProcess, known: set[tuple[int, ...]] | None = None) -> None:
        """Up: its diagnostics come, a subscription to points not among ``known`` (those
        before it started) is matched, query_points answers."""
        from uncertain_facade_map.srv import QueryPoints

        assert self.client is not None
        deadline = time.monotonic() + self.opts.start_timeout
        self.client.forget_clients()
        while True:
            if not node.alive():
                raise NodeDied(f'the node ended with status {node.proc.returncode}: '
                               f'{exception_text(node.log_since(0)) or node.log_since(0)[-500:]}')
            if time.monotonic() > deadline:
                raise NodeDied(f'the node did not come up within {self.opts.start_timeout} s')
            if (self.client.diag_time > node.started and self.client.pub.get_subscription_count() > 0
                    and (known is None or self.client.points_subscribers() - known)):
                break
            time.sleep(0.1)
        while self.client.call(QueryPoints, 'query_points', query_request(np.zeros((0, 3))), timeout=10.0) is None:
            if not node.alive() or time.monotonic() > deadline:
                raise NodeDied('query_points never answered')
            self.client.forget_clients()
        time.sleep(0.3)  # the points subscription matched; let the first cloud find it

    def alive(self) -> bool:
        return self.node is not None and self.node.alive()

    def publish(self, points: np.ndarray, stamp_ns: int | None = None, frame: str = 'map') -> None:
        assert self.client is not None
        self.client.pub.publish(cloud_message(points, stamp_ns or time.time_ns(), frame))

    def next_clouds(self, count: int) -> list[np.ndarray]:
        out = [cut_cloud(self.drive, self.next_cloud + i, self.opts.points, self.opts.seed) for i in range(count)]
        self.next_cloud += count
        return out

    def query(self, xyz: np.ndarray, resolution: float = 0.1, timeout: float = 60.0
              ) -> tuple[dict | None, int | None, Any]:
        """(answers, map version, response) of query_points; (None, None, response) when it failed."""
        from uncertain_facade_map.srv import QueryPoints

        assert self.client is not None
        response = self.client.call(QueryPoints, 'query_points', query_request(xyz, resolution), timeout)
        if response is None or not response.success:
            return None, None, response
        return answers_of(response), version_of(response.message), response

    def wait_settled(self, timeout: float) -> dict | None:
        """Diagnostics once nothing waits and the map is settled; None on timeout."""
        assert self.client is not None
        return self.client.diagnostics(after=time.monotonic(), until=settled, timeout=timeout)


def _param_value(opts: Options, name: str, default: Any) -> Any:
    """A parameter's value: an override, else the parameter file's, else ``default``."""
    for item in opts.overrides:
        key, _, value = item.partition(':=')
        if key == name:
            return type(default)(float(value)) if isinstance(default, (int, float)) else value
    try:
        import yaml

        doc = yaml.safe_load(Path(opts.params).read_text())
        node = next(iter(doc.values()))['ros__parameters']
        section, key = name.split('.')
        return node.get(section, {}).get(key, default)
    except (OSError, ValueError, KeyError, AttributeError, StopIteration, ImportError):
        return default


# ------------------------------------------------------------------------------------------
# Accounting
# ------------------------------------------------------------------------------------------
def accounting(values: dict, published: int, start: dict | None = None) -> dict:
    """Every cloud and point accounted for in the node's counters.

    Checks: received (since ``start``) = published (less the node's own estimate of clouds
    lost before they reached it, when it gives one); received = the sum of the parts, for
    clouds and for points.
    """
    start = start or {}
    out: dict[str, Any] = {'missing_keys': []}
    for kind, parts in (('clouds', CLOUD_PARTS), ('points', POINT_PARTS)):
        received, key = counter(values, f'{kind}_received')
        if key != f'{kind}_received':
            out['missing_keys'].append(f'{kind}_received')
        got = {}
        for part in parts:
            value, used = counter(values, f'{kind}_{part}')
            if used != f'{kind}_{part}':
                out['missing_keys'].append(f'{kind}_{part}')
            got[part] = value or 0
        total = sum(got.values())
        out[kind] = {'received': received, **got, 'sum': total,
                     'ok': received is not None and total == received}
    received, _ = counter(values, 'clouds_received')
    received_start, _ = counter(start, 'clouds_received') if start else (0, None)
    delta = (received or 0) - (received_start or 0)
    missed = as_int(values, 'clouds_missed_estimate')
    if missed is not None:
        missed -= as_int(start, 'clouds_missed_estimate') or 0
    out['published'] = published
    out['received_since_start'] = delta
    out['lost'] = published - delta
    out['missed_estimate'] = missed
    # Clouds lost on the way (best-effort input) are accounted for when the node counts them.
    # The node estimates them from gaps in the stamps: losses after the last cloud it got
    # are invisible to it, so the estimate may fall short by a few (ESTIMATE_TOLERANCE).
    out['published_ok'] = delta == published or (
        missed is not None and abs(delta + missed - published) <= ESTIMATE_TOLERANCE * published + 10)
    out['ok'] = out['published_ok'] and out['clouds']['ok'] and out['points']['ok']
    return out


# ------------------------------------------------------------------------------------------
# Soak
# ------------------------------------------------------------------------------------------
def _query_client_main(conn: Any, domain: int, xyz: np.ndarray, period: float) -> None:
    """The query client's process: calls query_points every ``period`` seconds and sends
    (end time, seconds, answered) per call until ``conn`` says stop (or closes)."""
    import signal as _signal

    from uncertain_facade_map.srv import QueryPoints

    _signal.signal(_signal.SIGINT, _signal.SIG_IGN)
    client = Client(domain)
    request = query_request(xyz, 0.0)
    try:
        while not conn.poll(0):
            t = time.monotonic()
            response = client.call(QueryPoints, 'query_points', request, timeout=60.0)
            done = time.monotonic()
            conn.send((done, done - t, response is not None and response.success))
            if conn.poll(max(0.0, period - (done - t))):
                break
    except (EOFError, OSError, BrokenPipeError):
        pass
    finally:
        client.close()


class QueryLoop(threading.Thread):
    """Calls query_points every ``period`` seconds from a process of its own, as a
    localisation node would (not from the publishing process, whose own load would count
    in the latency); keeps (end time, seconds, answered) per call (monotonic clock, which
    processes share)."""

    def __init__(self, session: Session, xyz: np.ndarray, period: float) -> None:
        super().__init__(daemon=True, name='soak_queries')
        self.session = session
        self.xyz = xyz
        self.period = period
        self.records: list[tuple[float, float, bool]] = []
        self._conn: Any = None
        self._process: Any = None

    def run(self) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context('spawn')
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(target=_query_client_main, name='soak_queries', daemon=True,
                                    args=(child, self.session.domain, self.xyz, self.period))
        self._process.start()
        child.close()
        while True:
            try:
                self.records.append(self._conn.recv())
            except (EOFError, OSError):
                return

    def stop(self) -> None:
        if self._conn is not None:
            with contextlib.suppress(OSError, BrokenPipeError):
                self._conn.send('stop')
        if self._process is not None:
            self._process.join(70)
            if self._process.is_alive():
                self._process.kill()
        self.join(10)

    def window(self, t0: float, t1: float) -> dict:
        """p50, p95 (ms), calls and failures of the calls ending in (t0, t1]."""
        got = [r for r in self.records if t0 < r[0] <= t1]
        ok = [r[1] for r in got if r[2]]
        return {'calls': len(got), 'failed': len(got) - len(ok),
                'p50_ms': round(1e3 * float(np.percentile(ok, 50)), 1) if ok else None,
                'p95_ms': round(1e3 * float(np.percentile(ok, 95)), 1) if ok else None}


#: Diagnostics kept in the samples: the counters, the map's size, the timings.
SAMPLE_PREFIXES = ('query_', 'reading_', 'clouds_', 'points_', 'poses_', 'latency', 'last_update', 'map_', 'facades', 'buildings',
                   'settled', 'flushes', 'queries', 'callback_errors', 'saves', 'published_')


def take_sample(session: Session, t0: float, last: float, queries: QueryLoop, published: int) -> dict:
    """One sample: memory, queue, counters, query latencies since the last sample."""
    assert session.client is not None and session.node is not None
    now = time.monotonic()
    per = session.node.memory_by_process()
    rss, hwm = sum(r for r, _ in per.values()), sum(h for _, h in per.values())
    values = dict(session.client.diag_values)
    mapping_pid = as_int(values, 'mapping_pid')
    parts: dict[str, float] = {}  # RSS MB of the node, its mapping process and the other (published maps)
    for pid, (kb, _) in per.items():
        name = 'node' if pid == session.node.pid else 'mapping' if pid == mapping_pid else 'other'
        parts[name] = round(parts.get(name, 0.0) + kb / 1024, 1)
    waiting, _ = counter(values, 'clouds_waiting')
    sample = {'t': round(now - t0, 1), 'rss_mb': round(rss / 1024, 1), 'hwm_mb': round(hwm / 1024, 1),
              'published': published, 'queue': waiting, 'alive': session.node.alive(),
              'diagnostics_age_s': round(now - session.client.diag_time, 1) if session.client.diag_time else None,
              'query': queries.window(last, now),
              'rss_parts_mb': parts}
    sample['counters'] = {k: v for k, v in values.items() if k.startswith(SAMPLE_PREFIXES)}
    return sample


def run_soak(session: Session) -> dict:
    """Publish at the rate for the time, sample every sample_period, check the accounting."""
    opts = session.opts
    assert session.client is not None
    node = session.start_node(tag='soak')
    start = session.client.diagnostics(after=time.monotonic(), timeout=30) or {}
    total = max(1, int(round(opts.minutes * 60 * opts.rate)))
    say(opts, f'soak: {total} clouds of {opts.points:,} points at {opts.rate} Hz '
              f'({opts.minutes * 60:.0f} s), node pid {node.pid}')
    queries = QueryLoop(session, probe_points(session.drive, opts.query_points, opts.seed + 1), opts.query_period)
    queries.start()
    t0 = time.monotonic()
    samples: list[dict] = [take_sample(session, t0, t0, queries, 0)]
    stamp0 = time.time_ns()
    last_sample = t0
    late = 0.0
    published = 0
    for k in range(total):
        due = t0 + k / opts.rate
        while time.monotonic() < due:
            time.sleep(max(0.0, min(0.01, due - time.monotonic())))
            if time.monotonic() - last_sample >= opts.sample_period:
                samples.append(take_sample(session, t0, last_sample, queries, published))
                last_sample = time.monotonic()
                say(opts, _sample_line(samples[-1]))
        late = max(late, time.monotonic() - due)
        points = cut_cloud(session.drive, session.next_cloud, opts.points, opts.seed)
        session.next_cloud += 1
        session.client.pub.publish(cloud_message(points, stamp0 + int(k * 1e9 / opts.rate)))
        published += 1
        if not node.alive():
            break
    publish_seconds = time.monotonic() - t0
    say(opts, f'soak: published {published} clouds in {publish_seconds:.1f} s; waiting for the queue to empty')
    final = drain(session, published, start, t0, samples, queries, last_sample)
    queries.stop()
    samples.append(take_sample(session, t0, samples[-1]['t'] + t0 if samples else t0, queries, published))
    report = {'settings': {'rate': opts.rate, 'points': opts.points, 'minutes': opts.minutes,
                           'clouds': total, 'query_points': opts.query_points, 'query_period': opts.query_period,
                           'sample_period': opts.sample_period},
              'published': published, 'publish_seconds': round(publish_seconds, 1),
              'publish_late_max_s': round(late, 2), 'alive': node.alive(), 'samples': samples,
              'growth': growth(samples),
              'queries': queries.window(0, float('inf')), 'final_counters': final,
              'drain_seconds': round(time.monotonic() - t0 - publish_seconds, 1)}
    report['accounting'] = accounting(final or {}, published, start)
    report['drained'] = bool(final) and settled(final)
    if not node.alive():
        report['exception'] = exception_text(node.log_since(0))
    return report


def drain(session: Session, published: int, start: dict, t0: float, samples: list, queries: QueryLoop,
          last_sample: float) -> dict | None:
    """Sample on until everything published is counted and the queue is empty (or the timeout)."""
    opts = session.opts
    assert session.client is not None and session.node is not None
    deadline = time.monotonic() + opts.drain_timeout
    received_start, _ = counter(start, 'clouds_received')

    stable = {'received': None, 'since': time.monotonic()}

    def done(v: dict) -> bool:
        received, _ = counter(v, 'clouds_received')
        if received != stable['received']:
            stable.update(received=received, since=time.monotonic())
        rejected = as_int(v, 'clouds_rejected') or 0
        # Today's clouds_in leaves the rejected clouds out.
        seen = (received or 0) - (received_start or 0) + (0 if 'clouds_received' in v else rejected)
        # Everything arrived, or what was lost on the way will not come any more.
        return settled(v) and (seen >= published or time.monotonic() - stable['since'] > 5.0)

    while time.monotonic() < deadline and session.node.alive():
        got = session.client.diagnostics(after=time.monotonic(), until=done, timeout=min(opts.sample_period, 5.0))
        if time.monotonic() - last_sample >= opts.sample_period:
            samples.append(take_sample(session, t0, last_sample, queries, published))
            last_sample = time.monotonic()
            say(opts, _sample_line(samples[-1]))
        if got is not None:
            time.sleep(0.5)  # the counters of the last cloud, published once more
            return session.client.diagnostics(after=time.monotonic(), timeout=10) or got
    return session.client.diagnostics(after=time.monotonic(), timeout=10)


def _sample_line(s: dict) -> str:
    c = s['counters']
    return (f't={s["t"]:.0f}s rss={s["rss_mb"]:.0f}MB queue={s["queue"]} published={s["published"]} '
            f'received={c.get("clouds_received", c.get("clouds_in"))} mapped={c.get("clouds_mapped")} '
            f'dropped={c.get("clouds_dropped")} map_points={c.get("map_points")} '
            f'update={c.get("last_update_seconds")}s cpu={c.get("last_update_cpu_seconds")}s query p95={s["query"]["p95_ms"]}ms')


# ------------------------------------------------------------------------------------------
# Kills during save_map
# ------------------------------------------------------------------------------------------
def file_digest(path: Path) -> str | None:
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def temporary_files(path: Path) -> list[str]:
    """The hidden temporary files of saves of ``path`` (``.NAME.*.tmp`` next to it)."""
    return sorted(p.name for p in path.parent.glob(f'.{path.name}.*.tmp'))


def save_async(session: Session, path: Path) -> concurrent.futures.Future:
    """Ask for save_map(path) without waiting."""
    from uncertain_facade_map.srv import SaveMap

    assert session.client is not None
    client = session.client
    future: concurrent.futures.Future = concurrent.futures.Future()

    def call() -> None:
        try:
            future.set_result(client.call(SaveMap, 'save_map', SaveMap.Request(path=str(path)), 300.0))
        except Exception as exc:  # noqa: BLE001 - handed to the waiting thread
            future.set_exception(exc)

    # A daemon thread: a call to a node killed meanwhile must not hold up the exit.
    threading.Thread(target=call, daemon=True, name='soak_save').start()
    return future


def watch_write(path: Path, timeout: float) -> tuple[float | None, float | None]:
    """Seconds until a temporary file of ``path`` appears and until it is gone again (None: never)."""
    t0 = time.monotonic()
    seen = None
    while time.monotonic() - t0 < timeout:
        present = bool(temporary_files(path))
        if present and seen is None:
            seen = time.monotonic() - t0
        if seen is not None and not present:
            return seen, time.monotonic() - t0
        time.sleep(0.0005)
    return seen, None


def calibrate_save(session: Session, path: Path) -> dict:
    """One whole save: how long the call takes and how long its temporary file lives."""
    t = time.monotonic()
    future = save_async(session, path)
    appeared, gone = watch_write(path, 120.0)
    response = future.result()
    return {'seconds': round(time.monotonic() - t, 3), 'tmp_appeared_s': appeared,
            'write_seconds': None if appeared is None or gone is None else round(gone - appeared, 4),
            'success': bool(response and response.success), 'message': getattr(response, 'message', None)}


def kill_fraction(session: Session, index: int) -> float:
    """Where kill ``index`` strikes, as a share of the file written: the first mid-write (0.5),
    the others drawn from [0, 1.1) (above 1: once the temporary file is gone, after the rename)."""
    return 0.5 if index == 0 else float(session.rng.uniform(0.0, 1.1))


def tmp_bytes(path: Path) -> int | None:
    """Bytes written so far to the temporary file of a save of ``path``; None when there is none."""
    sizes = []
    for name in temporary_files(path):
        with contextlib.suppress(OSError):
            sizes.append((path.parent / name).stat().st_size)
    return max(sizes) if sizes else None


def kill_during_save(session: Session, path: Path, fraction: float, expected_bytes: int) -> dict:
    """save_map, then SIGKILL once ``fraction`` of the expected bytes are in the temporary file
    (``fraction`` > 1: once the temporary file is gone again)."""
    assert session.node is not None
    before = file_digest(path)
    t = time.monotonic()
    save_async(session, path)
    deadline = t + 120.0
    appeared = None
    target = fraction * expected_bytes
    while time.monotonic() < deadline and session.node.alive():
        size = tmp_bytes(path)
        if size is not None and appeared is None:
            appeared = time.monotonic() - t
        if fraction <= 1.0 and size is not None and size >= target:
            break
        if size is None and (appeared is not None or file_digest(path) != before):
            break  # written and renamed (or written too fast to see)
        time.sleep(0.0002)
    written = tmp_bytes(path)
    session.node.kill()
    tmp = temporary_files(path)
    after = file_digest(path)
    moment = 'during write' if tmp else ('after the rename' if after != before else 'before the write')
    return {'fraction': round(fraction, 3), 'tmp_bytes_at_kill': written, 'expected_bytes': expected_bytes,
            'kill_after_s': round(time.monotonic() - t, 4),
            'tmp_appeared_s': None if appeared is None else round(appeared, 4),
            'moment': moment, 'tmp_at_kill': tmp, 'old_digest': before, 'digest': after}


def check_file(path: Path, old_digest: str | None) -> tuple[str, str]:
    """('old' | 'new' | 'none' | 'missing' | 'damaged', detail) of the map file after a kill."""
    from uncertain_facade_map.errors import FacadeMapError
    from uncertain_facade_map.io.map_file import load_map

    digest = file_digest(path)
    if digest is None:
        return ('none', '') if old_digest is None else ('missing', 'the old file is gone')
    try:
        fmap = load_map(path)
    except (FacadeMapError, OSError, ValueError) as exc:
        return 'damaged', str(exc)[:300]
    state = 'old' if digest == old_digest else 'new'
    return state, f'{len(fmap.facades)} façades, {fmap.n_points} points'


def feed(session: Session, clouds: int, timeout: float, attempts: int = 3) -> dict | None:
    """Publish ``clouds`` more clouds of the drive, each again (the next one) until the node
    counts it (a cloud published just after a restart may go to the dead node's subscription),
    then wait until the map settled; its diagnostics, None on timeout."""
    assert session.client is not None
    for _ in range(clouds):
        for _ in range(attempts):
            before = dict(session.client.diag_values)
            t = time.monotonic()
            session.publish(session.next_clouds(1)[0])
            if wait_counted(session, before, t, 10.0) is not None:
                break
    return session.wait_settled(timeout)


def run_kills(session: Session) -> dict:
    """SIGKILL the node during save_map ``kills`` times; check the file, tmp files and answers after each."""
    opts = session.opts
    assert session.client is not None
    folder = session.out / 'kills'
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / 'map.npz'
    for old in [path, *[folder / name for name in temporary_files(path)]]:
        old.unlink(missing_ok=True)
    if not session.alive():
        session.start_node(tag='kills')
    seeded = session.wait_settled(opts.settle_timeout)
    if seeded is not None and not as_int(seeded, 'facades'):
        say(opts, 'kills: the map is empty; mapping a few clouds first')
        feed(session, 3, opts.settle_timeout)
    calibration = calibrate_save(session, path)
    say(opts, f'kills: a whole save takes {calibration["seconds"]} s (write {calibration["write_seconds"]} s)')
    results = []
    for i in range(opts.kills):
        results.append(one_kill(session, path, i))
        r = results[-1]
        say(opts, f'kill {i + 1}/{opts.kills}: {r["moment"]}, file {r["file"]}, tmp after restart '
                  f'{r["tmp_after_restart"] or "none"}, answers identical {r["answers_identical"]}')
    checks = {'file_whole': all(r['file'] in ('old', 'new', 'none') for r in results),
              'no_tmp_after_restart': all(not r['tmp_after_restart'] for r in results),
              'answers_identical': all(r['answers_identical'] for r in results),
              'restarted': all(r['restarted'] for r in results)}
    return {'path': str(path), 'calibration': calibration, 'kills': results, 'checks': checks,
            'moments': {m: sum(r['moment'] == m for r in results)
                        for m in ('during write', 'before the write', 'after the rename')}}


def one_kill(session: Session, path: Path, index: int) -> dict:
    """Change the map, kill during a save, check the file, restart on it, check tmp files and answers."""
    opts = session.opts
    feed(session, 1, opts.settle_timeout)
    # The map grew by one cloud since the last save: about as many bytes again.
    expected = path.stat().st_size if path.exists() else 1
    result: dict[str, Any] = {'index': index,
                              **kill_during_save(session, path, kill_fraction(session, index), expected)}
    result['file'], result['file_detail'] = check_file(path, result['old_digest'])
    result['restarted'] = False
    result['tmp_after_restart'] = []
    result['answers_identical'] = False
    try:
        session.start_node(path if path.exists() else None, tag=f'kill{index + 1}')
        result['restarted'] = True
    except NodeDied as exc:
        result['exception'] = str(exc)[:500]
        return result
    result['tmp_after_restart'] = temporary_files(path)
    for name in result['tmp_after_restart']:  # each kill is judged on its own leftovers
        (path.parent / name).unlink(missing_ok=True)
    probe = map_probe(path, 500, opts.seed + index) if path.exists() else session.probe
    answers, version, response = session.query(probe)
    result['version_after_restart'] = version
    if answers is None:
        result['exception'] = f'query_points failed: {getattr(response, "message", "no answer")}'
    elif path.exists():
        result['answers_identical'] = same_answers(answers, offline_answers(path, probe))
        result['probe_on_facades'] = int((answers['facade'] >= 0).sum())
    else:
        result['answers_identical'] = bool(np.all(answers['facade'] == -1))
    return result


# ------------------------------------------------------------------------------------------
# Fuzz
# ------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Case:
    """One kind of bad (or, for control, valid) input.

    Attributes:
        name: unique name (a pytest parameter).
        group: cloud, query, save, load, get_map or pose.
        valid: the input is valid: the map may change.
        act: sends the input; returns details (a service's success and message).
        topic: the input goes through a topic: wait until the node counted it.
        about: one line.
    """

    name: str
    group: str
    valid: bool
    act: Callable[[FuzzContext], dict]
    topic: bool = False
    about: str = ''


class FuzzContext:
    """What the cases need: the session, a folder, the baseline map and sample points."""

    def __init__(self, session: Session, folder: Path, baseline: Path) -> None:
        self.session = session
        self.folder = folder
        self.baseline = baseline
        drive = session.drive
        # Points of the part of the drive the node was fed: valid clouds of them repeat the map.
        part = drive[:max(1, min(len(drive), session.next_cloud * session.opts.points))]
        building = part[part['class'] == 1]
        self.points = building[np.random.default_rng(session.opts.seed).choice(len(building), 500)]
        self.probe = map_probe(baseline, 500, session.opts.seed)
        self._stamp = time.time_ns()

    def stamp(self) -> int:
        self._stamp += 100_000_000
        return self._stamp

    def message(self, points: np.ndarray | None = None, frame: str = 'map') -> Any:
        return cloud_message(self.points if points is None else points, self.stamp(), frame)

    def send(self, msg: Any) -> dict:
        assert self.session.client is not None
        self.session.client.pub.publish(msg)
        return {}

    def call(self, srv_type: Any, name: str, request: Any, timeout: float = 120.0,
             extra: Callable[[Any], dict] | None = None) -> dict:
        """Call a service; its success, message (or ``extra(response)``) and the seconds it took."""
        assert self.session.client is not None
        t = time.monotonic()
        response = self.session.client.call(srv_type, name, request, timeout)
        out = {'answered': response is not None, 'call_seconds': round(time.monotonic() - t, 3)}
        if response is not None:
            out['success'] = getattr(response, 'success', None)
            out['message'] = str(getattr(response, 'message', ''))[:300]
            if extra is not None:
                out.update(extra(response))
        return out


def _field(msg: Any, name: str) -> Any:
    return next(f for f in msg.fields if f.name == name)


def _with_fields(msg: Any, fields: list) -> Any:
    msg.fields = fields
    return msg


def _data(msg: Any, data: bytes) -> Any:
    msg.data = array('B', data)
    return msg


def _points_with(ctx: FuzzContext, **values: Any) -> np.ndarray:
    points = ctx.points.copy()
    for name, value in values.items():
        points[name] = value
    return points


def _retyped(ctx: FuzzContext, dtype: list, **values: Any) -> np.ndarray:
    """The sample points in another dtype (names kept), with ``values`` set."""
    out = np.zeros(len(ctx.points), dtype)
    for name in out.dtype.names:
        if name in ctx.points.dtype.names:
            out[name] = ctx.points[name]
    for name, value in values.items():
        out[name] = value
    return out


def _big_endian(ctx: FuzzContext) -> Any:
    """A correct big-endian cloud (flag and data): valid."""
    msg = ctx.message()
    be = ctx.points.astype(ctx.points.dtype.newbyteorder('>'))
    msg.is_bigendian = True
    return _data(msg, be.tobytes())


def _cloud(name: str, build: Callable[[FuzzContext], Any], about: str, valid: bool = False) -> Case:
    return Case(name, 'cloud', valid, lambda ctx: ctx.send(build(ctx)), topic=True, about=about)


def _set(msg: Any, **values: Any) -> Any:
    for key, value in values.items():
        setattr(msg, key, value)
    return msg


def cloud_cases() -> list[Case]:
    from sensor_msgs.msg import PointCloud2, PointField

    def pf(name: str, offset: int, datatype: int, count: int = 1) -> Any:
        return PointField(name=name, offset=offset, datatype=datatype, count=count)

    def fields_but(msg: Any, name: str) -> Any:
        return _with_fields(msg, [f for f in msg.fields if f.name != name])

    def retype(msg: Any, name: str, datatype: int, count: int = 1, offset: int | None = None) -> Any:
        f = _field(msg, name)
        f.datatype, f.count = datatype, count
        if offset is not None:
            f.offset = offset
        return msg

    def renamed(msg: Any, old: str, new: str) -> Any:
        _field(msg, old).name = new
        return msg

    def dup(msg: Any, name: str) -> Any:
        f = _field(msg, name)
        return _with_fields(msg, [*msg.fields, pf(name, f.offset, f.datatype, f.count)])

    def empty(frame: str = 'map') -> Any:
        msg = PointCloud2()
        msg.header.frame_id = frame
        return msg

    f32max = float(np.finfo(np.float32).max)
    return [
        _cloud('point_step_short', lambda c: _set(c.message(), point_step=c.message().point_step - 4),
               'point_step 4 bytes short of the fields'),
        _cloud('point_step_long', lambda c: _set(c.message(), point_step=c.message().point_step + 4),
               'point_step 4 bytes longer than the data has'),
        _cloud('point_step_zero', lambda c: _set(c.message(), point_step=0), 'point_step 0'),
        _cloud('point_step_huge', lambda c: _set(c.message(), point_step=2**32 - 1), 'point_step 2^32-1'),
        _cloud('row_step_short', lambda c: _set(c.message(), row_step=c.message().row_step - 1),
               'row_step one byte short of width * point_step'),
        _cloud('row_step_long', lambda c: _set(c.message(), row_step=c.message().row_step + 64),
               'row_step longer than the data'),
        _cloud('row_step_zero', lambda c: _set(c.message(), row_step=0), 'row_step 0'),
        _cloud('data_truncated_byte', lambda c: _data(c.message(), bytes(c.message().data)[:-1]),
               'data one byte short'),
        _cloud('data_truncated_half', lambda c: _data(c.message(), bytes(c.message().data)[:len(c.message().data) // 2]),
               'half the data'),
        _cloud('data_empty', lambda c: _data(c.message(), b''), 'no data, width > 0'),
        _cloud('data_extra', lambda c: _data(c.message(), bytes(c.message().data) + b'\0' * 7),
               '7 bytes more data than row_step * height'),
        _cloud('missing_x', lambda c: fields_but(c.message(), 'x'), 'no x field'),
        _cloud('missing_y', lambda c: fields_but(c.message(), 'y'), 'no y field'),
        _cloud('missing_z', lambda c: fields_but(c.message(), 'z'), 'no z field'),
        _cloud('no_fields', lambda c: _with_fields(c.message(), []), 'no fields at all'),
        _cloud('duplicate_x', lambda c: dup(c.message(), 'x'), 'x twice'),
        _cloud('duplicate_class', lambda c: dup(c.message(), 'class'), 'class twice'),
        _cloud('x_datatype_0', lambda c: retype(c.message(), 'x', 0), 'x of datatype 0 (none)'),
        _cloud('x_datatype_9', lambda c: retype(c.message(), 'x', 9), 'x of datatype 9 (unknown)'),
        _cloud('x_datatype_255', lambda c: retype(c.message(), 'x', 255), 'x of datatype 255'),
        _cloud('x_as_int32', lambda c: retype(c.message(), 'x', 5),
               'x declared INT32 over float bytes: coordinates about 1e9 m'),
        _cloud('x_as_float64', lambda c: retype(c.message(), 'x', 8),
               'x declared FLOAT64 over the bytes of x and y'),
        _cloud('x_count_zero', lambda c: retype(c.message(), 'x', 7, 0), 'x with count 0'),
        _cloud('x_count_three', lambda c: retype(c.message(), 'x', 7, 3), 'x with count 3 (x, y, z in one field)'),
        _cloud('x_count_huge', lambda c: retype(c.message(), 'x', 7, 2**31), 'x with count 2^31'),
        _cloud('x_offset_past_step', lambda c: retype(c.message(), 'x', 7, 1, 10_000), 'x at offset 10000'),
        _cloud('field_empty_name', lambda c: renamed(c.message(), 'building_id', ''), 'a field without a name'),
        _cloud('class_as_float32', lambda c: c.message(_retyped(c, [('x', 'f4'), ('y', 'f4'), ('z', 'f4'),
                                                                    ('class', 'f4')], **{'class': 1.5})),
               'class field FLOAT32 (1.5)'),
        _cloud('class_past_step', lambda c: retype(c.message(), 'class', 8), 'class FLOAT64 running past point_step'),
        _cloud('class_renamed', lambda c: renamed(c.message(), 'class', 'label'),
               'the class field under another name (label): a cloud without classes', valid=True),
        _cloud('class_not_building', lambda c: c.message(_points_with(c, **{'class': 2})),
               'every point of a non-building class', valid=True),
        _cloud('building_id_float_nan', lambda c: c.message(_retyped(c, [('x', 'f4'), ('y', 'f4'), ('z', 'f4'),
                                                                         ('class', 'u1'), ('building_id', 'f4')],
                                                                     building_id=np.nan)),
               'building_id FLOAT32, all NaN'),
        _cloud('nan_all', lambda c: c.message(_points_with(c, x=np.nan, y=np.nan, z=np.nan)), 'every coordinate NaN'),
        _cloud('nan_x', lambda c: c.message(_points_with(c, x=np.nan)), 'every x NaN'),
        _cloud('inf_all', lambda c: c.message(_points_with(c, x=np.inf, y=np.inf, z=np.inf)), 'every coordinate +inf'),
        _cloud('neg_inf_z', lambda c: c.message(_points_with(c, z=-np.inf)), 'every z -inf'),
        _cloud('nan_dense_flag', lambda c: _set(c.message(_points_with(c, y=np.nan)), is_dense=True),
               'is_dense True, every y NaN'),
        _cloud('coords_1e30', lambda c: c.message(_points_with(c, x=1e30, y=1e30, z=1e30)),
               'absurd but finite: every coordinate 1e30'),
        _cloud('coords_neg_1e30', lambda c: c.message(_points_with(c, x=-1e30)), 'every x -1e30'),
        _cloud('coords_1e20_z', lambda c: c.message(_points_with(c, z=1e20)), 'every z 1e20'),
        _cloud('coords_f32_max', lambda c: c.message(_points_with(c, x=f32max, y=-f32max)),
               'x and -y at the float32 maximum'),
        _cloud('coords_f64_1e300', lambda c: c.message(_retyped(c, [('x', 'f8'), ('y', 'f8'), ('z', 'f8'),
                                                                    ('class', 'u1')], x=1e300, y=1e300, z=1e300)),
               'float64 coordinates 1e300'),
        _cloud('origins_1e30', lambda c: c.message(_points_with(c, origin_x=1e30, origin_y=1e30)),
               'sensor origins 1e30 m away'),
        _cloud('origins_nan', lambda c: c.message(_points_with(c, origin_x=np.nan, origin_y=np.nan, origin_z=np.nan)),
               'sensor origins NaN', valid=True),
        _cloud('bigendian_flag_le_data', lambda c: _set(c.message(), is_bigendian=True),
               'flagged big-endian, data little-endian: garbage coordinates'),
        _cloud('bigendian_correct', _big_endian, 'a correct big-endian cloud', valid=True),
        _cloud('huge_width_little_data', lambda c: _set(c.message(), width=4_000_000),
               'width 4 000 000 (under node.max_cloud_points) with 500 points of data'),
        _cloud('huge_width_height', lambda c: _set(c.message(), width=2**32 - 1, height=2**32 - 1),
               'width and height 2^32-1 with 500 points of data'),
        _cloud('height_zero', lambda c: _set(c.message(), height=0), 'height 0, width and data of 500 points'),
        _cloud('width_zero', lambda c: _set(c.message(), width=0), 'width 0, data of 500 points'),
        _cloud('height_two', lambda c: _set(c.message(), height=2), 'height 2, data of one row'),
        _cloud('empty_cloud', lambda c: empty(), 'an empty PointCloud2 (no fields, no data)'),
        _cloud('empty_with_fields', lambda c: c.message(c.points[:0]), 'zero points, the usual fields'),
        _cloud('frame_unknown', lambda c: c.message(frame='nowhere'), 'a frame without sensor_pose'),
        _cloud('frame_empty', lambda c: c.message(frame=''), 'an empty frame_id'),
        _cloud('one_point', lambda c: c.message(c.points[:1]), 'a single building point', valid=True),
    ]


def query_cases() -> list[Case]:
    from uncertain_facade_map.srv import QueryPoints

    def q(ctx: FuzzContext, xyz: Any, resolution: float = 0.0) -> dict:
        return ctx.call(QueryPoints, 'query_points', query_request(np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
                                                                   resolution))

    def probe(ctx: FuzzContext, n: int = 100) -> np.ndarray:
        return ctx.probe[:n]

    def huge(ctx: FuzzContext) -> dict:
        n = ctx.session.opts.huge_query or int(ctx.session.max_query_points) + 1
        return q(ctx, np.zeros((n, 3)))

    def with_bad(ctx: FuzzContext, value: float, column: int) -> dict:
        xyz = probe(ctx).copy()
        xyz[50, column] = value
        return q(ctx, xyz)

    cases = [
        ('query_nan_x', lambda c: q(c, [[np.nan, 0.0, 0.0]]), 'a point with x NaN'),
        ('query_nan_among_many', lambda c: with_bad(c, np.nan, 2), 'one NaN z among 100 points'),
        ('query_inf', lambda c: q(c, [[np.inf, 0.0, 0.0]]), 'a point with x +inf'),
        ('query_neg_inf_among_many', lambda c: with_bad(c, -np.inf, 1), 'one -inf y among 100 points'),
        ('query_empty', lambda c: q(c, np.zeros((0, 3))), 'no points (a zero-length array)'),
        ('query_resolution_nan', lambda c: q(c, probe(c), np.nan), 'resolution NaN'),
        ('query_resolution_negative', lambda c: q(c, probe(c), -0.1), 'resolution -0.1'),
        ('query_resolution_inf', lambda c: q(c, probe(c), np.inf), 'resolution +inf'),
        ('query_resolution_tiny', lambda c: q(c, probe(c), 1e-300), 'resolution 1e-300 m'),
        ('query_resolution_huge', lambda c: q(c, probe(c), 1e300), 'resolution 1e300 m'),
        ('query_point_1e30', lambda c: q(c, [[1e30, 1e30, 1e30]]), 'a point at 1e30 m'),
        ('query_over_limit', huge, 'service.max_query_points + 1 points (a huge request)'),
    ]
    return [Case(name, 'query', False, act, about=about) for name, act, about in cases]


def _write_npz(path: Path, arrays: dict) -> Path:
    with open(path, 'wb') as fh:
        np.savez(fh, **arrays)
    return path


def _baseline_arrays(ctx: FuzzContext) -> dict:
    with np.load(ctx.baseline, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def _with_meta(ctx: FuzzContext, change: Callable[[dict], None]) -> dict:
    arrays = _baseline_arrays(ctx)
    meta = json.loads(str(arrays['meta']))
    change(meta)
    arrays['meta'] = np.array(json.dumps(meta))
    return arrays


def _bad_file(ctx: FuzzContext, name: str, content: bytes | dict | None) -> Path:
    path = ctx.folder / name
    if isinstance(content, dict):
        return _write_npz(path, content)
    if content is not None:
        path.write_bytes(content)
    return path


def load_cases() -> list[Case]:
    from uncertain_facade_map.srv import LoadMap

    def load(ctx: FuzzContext, path: Path | str) -> dict:
        return ctx.call(LoadMap, 'load_map', LoadMap.Request(path=str(path)))

    def file_case(name: str, content: Callable[[FuzzContext], bytes | dict | None], about: str,
                  valid: bool = False) -> Case:
        return Case(name, 'load', valid, lambda c: load(c, _bad_file(c, f'{name}.npz', content(c))), about=about)

    def base(c: FuzzContext) -> bytes:
        return c.baseline.read_bytes()

    def flipped(c: FuzzContext) -> bytes:
        data = bytearray(base(c))
        mid = len(data) // 2
        data[mid:mid + 64] = bytes(255 - b for b in data[mid:mid + 64])
        return bytes(data)

    def without_facades(c: FuzzContext) -> dict:
        return {k: v for k, v in _baseline_arrays(c).items() if not k.startswith('facade/')}

    def meta_set(key: str, value: Any) -> Callable[[FuzzContext], dict]:
        return lambda c: _with_meta(c, lambda m: m.__setitem__(key, value))

    def random_bytes(prefix: bytes = b'') -> Callable[[FuzzContext], bytes]:
        return lambda c: prefix + np.random.default_rng(c.session.opts.seed).bytes(100_000)

    def meta_text(c: FuzzContext) -> dict:
        return {**_baseline_arrays(c), 'meta': np.array('{not json')}

    return [
        Case('load_missing', 'load', False, lambda c: load(c, c.folder / 'no_such_map.npz'), about='no such file'),
        Case('load_directory', 'load', False, lambda c: load(c, c.folder), about='a folder, not a file'),
        file_case('load_empty_file', lambda c: b'', 'an empty file'),
        file_case('load_truncated_half', lambda c: base(c)[:len(base(c)) // 2], 'the first half of a map file'),
        file_case('load_truncated_tail', lambda c: base(c)[:-100], 'a map file less its last 100 bytes'),
        file_case('load_flipped_bytes', flipped, '64 bytes inverted in the middle of a map file'),
        file_case('load_random_bytes', random_bytes(), '100 kB of random bytes'),
        file_case('load_random_zip_magic', random_bytes(b'PK\x03\x04'), 'random bytes after a zip signature'),
        file_case('load_json_text', lambda c: b'{"format": "uncertain_facade_map.map", "version": 3}', 'JSON text'),
        file_case('load_wrong_version', meta_set('version', 99), 'a map file of version 99'),
        file_case('load_version_zero', meta_set('version', 0), 'a map file of version 0'),
        file_case('load_version_text', meta_set('version', 'three'), 'version "three"'),
        file_case('load_wrong_format', meta_set('format', 'something.else'), 'another format name'),
        file_case('load_no_meta', lambda c: {k: v for k, v in _baseline_arrays(c).items() if k != 'meta'},
                  'an NPZ without the meta record'),
        file_case('load_meta_not_json', meta_text, 'meta that is not JSON'),
        file_case('load_missing_arrays', without_facades, 'meta lists façades whose arrays are missing'),
        file_case('load_other_npz', lambda c: {'x': np.arange(10)}, 'an NPZ of something else'),
        Case('load_absolute_outside', 'load', False, lambda c: load(c, _outside_copy(c)),
             about='a valid map outside the map folder, by its absolute path'),
        Case('load_dotdot', 'load', False, lambda c: load(c, f'{c.folder.name}/../../{_outside_copy(c).name}'),
             about='a valid map outside the map folder, through ".."'),
        Case('load_symlink_out', 'load', False, lambda c: load(c, _link_out(c, 'map_link.npz', _outside_copy(c))),
             about='a link in the map folder to a valid map outside it'),
        Case('load_oversized', 'load', False, lambda c: load(c, _sparse(c, 'huge.npz', 2**43)),
             about='an 8 TB (sparse) file: refused before it is read (persistence.max_load_mb)'),
        Case('load_manifest_escaping', 'load', False, lambda c: load(c, _escaping_tiled(c)),
             about="a tiled map in the map folder whose tile's file links to a map outside it"),
        Case('load_baseline', 'load', True, lambda c: load(c, c.baseline), about='the baseline map itself (valid)'),
    ]


def _outside_copy(c: FuzzContext) -> Path:
    """A copy of the baseline map next to the run's folder, outside the node's map folder."""
    outside = c.session.out.resolve().parent / f'{c.session.out.name}_outside.npz'
    if not outside.exists():
        shutil.copyfile(c.baseline, outside)
    return outside


def _link_out(c: FuzzContext, name: str, target: Path) -> Path:
    link = c.folder / name
    link.unlink(missing_ok=True)
    link.symlink_to(target)
    return link


def _sparse(c: FuzzContext, name: str, size: int) -> Path:
    path = c.folder / name
    with open(path, 'wb') as fh:
        fh.truncate(size)
    return path


def _escaping_tiled(c: FuzzContext) -> Path:
    """A tiled map in the map folder whose one tile's file is a link to a map outside it."""
    from uncertain_facade_map.io.map_file import load_map
    from uncertain_facade_map.tiling.manifest import Manifest, TileRecord, sha256_file, write_manifest

    folder = c.folder / 'escaping_tiles'
    (folder / 'tiles').mkdir(parents=True, exist_ok=True)
    outside = _outside_copy(c)
    _link_out(c, 'escaping_tiles/tiles/tile_0_0.npz', outside)
    fmap = load_map(outside)
    record = TileRecord('tile_0_0', (0, 0), (0.0, 0.0, 50.0, 50.0), (0.0,) * 6, 'tiles/tile_0_0.npz',
                        sha256_file(outside), [int(b) for b in fmap.buildings], len(fmap.facades), fmap.n_stored, '')
    from uncertain_facade_map.params import map_params_record

    write_manifest(folder, Manifest(50.0, tuple(float(x) for x in fmap.map_origin), map_params_record(fmap.params),
                                    {'tile_0_0': record}))
    return folder


def save_cases() -> list[Case]:
    from uncertain_facade_map.srv import SaveMap

    def save(ctx: FuzzContext, path: Path | str) -> dict:
        out = ctx.call(SaveMap, 'save_map', SaveMap.Request(path=str(path)))
        folder = Path(path).parent
        with contextlib.suppress(OSError):
            out['tmp_left'] = sorted(p.name for p in folder.glob('.*.tmp'))
        return out

    def victim(c: FuzzContext, name: str) -> Path:
        path = c.folder / name
        path.write_text('a file of someone else\n')
        return path

    def save_over(c: FuzzContext, path: Path) -> dict:
        """Save over ``path``, which must stay as it was: flagged as accepted if it changed."""
        before = path.read_bytes()
        out = save(c, path)
        if path.read_bytes() != before:
            return {**out, 'success': True, 'message': f'{path} was changed: {out.get("message")}'}
        return out

    def parent_is_file(c: FuzzContext) -> dict:
        blocker = c.folder / 'a_file'
        blocker.write_text('a file where a folder should be')
        return save(c, blocker / 'map.npz')

    def into_directory(c: FuzzContext) -> dict:
        target = c.folder / 'a_folder.npz'
        target.mkdir(exist_ok=True)
        return save(c, target)

    cases = [
        ('save_missing_folder', lambda c: save(c, '/nonexistent_soak_folder/sub/map.npz'), 'a folder that does not exist'),
        ('save_parent_is_file', parent_is_file, 'a path below a regular file'),
        ('save_onto_directory', into_directory, 'the path of an existing folder'),
        ('save_proc', lambda c: save(c, '/proc/soak_map.npz'), 'unwritable: /proc'),
        ('save_sys', lambda c: save(c, '/sys/soak_map.npz'), 'unwritable: /sys'),
        ('save_name_too_long', lambda c: save(c, c.folder / ('m' * 300 + '.npz')), 'a file name of 304 characters'),
        ('save_absolute_outside', lambda c: save_over(c, _outside_copy(c)),
         'an existing map outside the map folder, by its absolute path'),
        ('save_dotdot', lambda c: save(c, f'{c.folder.name}/../../escaped.npz'), 'a name leading out through ".."'),
        ('save_symlink_out', lambda c: save(c, _link_out(c, 'dir_link', c.session.out.resolve().parent) / 'out.npz'),
         'a name through a link in the map folder to a folder outside it'),
        ('save_over_text_file', lambda c: save_over(c, victim(c, 'victim.npz')),
         'an existing file that is not a map file (its bytes must stay)'),
        ('save_other_suffix', lambda c: save(c, c.folder / 'victim.txt'), 'a name without the .npz suffix'),
    ]
    out = [Case(name, 'save', False, act, about=about) for name, act, about in cases]
    out.append(Case('save_valid', 'save', True, lambda c: save(c, c.folder / 'saved.npz'),
                    about='a valid save (the map must not change)'))
    return out


def get_map_cases() -> list[Case]:
    from nav_msgs.srv import GetMap

    from uncertain_facade_map.srv import LoadMap

    def grid(response: Any) -> dict:
        info = response.map.info
        return {'success': True, 'message': f'grid {info.width} x {info.height} cells of {info.resolution:.3g} m'}

    def get(ctx: FuzzContext) -> dict:
        return ctx.call(GetMap, 'get_map', GetMap.Request(), extra=grid)

    def wide(name: str, offset: tuple[float, float]) -> Callable[[FuzzContext], dict]:
        def act(ctx: FuzzContext) -> dict:
            path = ctx.folder / f'{name}.npz'
            if not path.exists():
                build_two_blocks(path, offset)
            loaded = ctx.call(LoadMap, 'load_map', LoadMap.Request(path=str(path)))
            if not loaded.get('success'):
                return {**loaded, 'answered': False, 'message': f'the wide map did not load: {loaded.get("message")}'}
            t = time.monotonic()
            got = get(ctx)
            got['get_map_seconds'] = round(time.monotonic() - t, 2)
            return got
        return act

    return [
        Case('get_map_baseline', 'get_map', True, get, about='get_map of the baseline map'),
        Case('get_map_wide_200m', 'get_map', True, wide('wide_200m', (200.0, 200.0)),
             about='get_map of a map 200 m wide (and deep): two small blocks 200 m apart in x and in y'),
        Case('get_map_wide_200m_x', 'get_map', True, wide('wide_200m_x', (200.0, 0.0)),
             about='get_map of a map 200 m long: two small blocks 200 m apart along x'),
    ]


def block_points(origin: tuple[float, float], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A small block's walls (an 8 m x 6 m footprint, 6 m high): points and sensor origins."""
    rng = np.random.default_rng(seed)
    x0, y0 = origin
    walls = [((x0, y0), (x0 + 8.0, y0), (0.0, -1.0)), ((x0, y0 + 6.0), (x0 + 8.0, y0 + 6.0), (0.0, 1.0)),
             ((x0, y0), (x0, y0 + 6.0), (-1.0, 0.0)), ((x0 + 8.0, y0), (x0 + 8.0, y0 + 6.0), (1.0, 0.0))]
    pts, origins = [], []
    for (ax, ay), (bx, by), (nx, ny) in walls:
        n = 800
        t = rng.random(n)
        z = rng.uniform(0.0, 6.0, n)
        depth = rng.normal(0.0, 0.02, n)
        xyz = np.stack([ax + t * (bx - ax) + nx * depth, ay + t * (by - ay) + ny * depth, z], 1)
        pts.append(xyz)
        origins.append(np.stack([ax + t * (bx - ax) + nx * 10.0, ay + t * (by - ay) + ny * 10.0,
                                 np.full(n, 1.8)], 1))
    return np.vstack(pts), np.vstack(origins)


def build_two_blocks(path: Path, offset: tuple[float, float], params_file: Path | None = None) -> Path:
    """Map two small blocks ``offset`` apart offline (the node's parameters) and save the map."""
    from uncertain_facade_map.io.map_file import save_map
    from uncertain_facade_map.io.parameter_file import load_config
    from uncertain_facade_map.mapping.facade_map import FacadeMap
    from uncertain_facade_map.params import map_params

    config = load_config(params_file or DEFAULT_PARAMS)
    fmap = FacadeMap(map_params(config), np.zeros(3))
    for building, origin in enumerate(((0.0, 0.0), offset)):
        xyz, origins = block_points(origin, building)
        fmap.add_points(xyz, np.full(len(xyz), building, np.int64), origins)
    fmap.flush()
    save_map(fmap, path)
    return path


def pose_cases() -> list[Case]:
    from geometry_msgs.msg import TransformStamped

    def pose_then_cloud(rotation: tuple, translation: tuple, frame: str = 'map', cloud_dt: float = 0.0
                        ) -> Callable[[FuzzContext], dict]:
        def act(ctx: FuzzContext) -> dict:
            stamp = ctx.stamp()
            child = f'soak_sensor_{stamp}'
            msg = TransformStamped()
            msg.header.frame_id = frame
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            msg.child_frame_id = child
            t = msg.transform.translation
            t.x, t.y, t.z = (float(v) for v in translation)
            q = msg.transform.rotation
            q.x, q.y, q.z, q.w = (float(v) for v in rotation)
            assert ctx.session.client is not None
            ctx.session.client.pose_pub.publish(msg)
            time.sleep(0.3)  # the pose first
            # The sample points in the sensor frame of a valid pose at the origin (identity).
            ctx.session.client.pub.publish(cloud_message(ctx.points, stamp + int(cloud_dt * 1e9), child))
            return {}
        return act

    nan, inf = float('nan'), float('inf')
    cases = [
        ('pose_zero_quaternion', (0, 0, 0, 0), (0, 0, 0), 'quaternion (0, 0, 0, 0)'),
        ('pose_non_unit_quaternion', (0, 0, 0, 2), (0, 0, 0), 'quaternion (0, 0, 0, 2): norm 2'),
        ('pose_tiny_quaternion', (0, 0, 0, 1e-20), (0, 0, 0), 'quaternion of norm 1e-20'),
        ('pose_nan_quaternion', (0, 0, nan, 1), (0, 0, 0), 'a NaN in the quaternion'),
        ('pose_inf_quaternion', (inf, 0, 0, 1), (0, 0, 0), 'an inf in the quaternion'),
        ('pose_nan_translation', (0, 0, 0, 1), (nan, 0, 0), 'translation x NaN'),
        ('pose_inf_translation', (0, 0, 0, 1), (0, -inf, 0), 'translation y -inf'),
        ('pose_huge_translation', (0, 0, 0, 1), (1e30, 1e30, 0), 'translation 1e30 m'),
    ]
    out = [Case(name, 'pose', False, pose_then_cloud(r, t), topic=True,
                about=f'{about}, then a cloud in its frame') for name, r, t, about in cases]
    out += [
        Case('pose_wrong_parent_frame', 'pose', False, pose_then_cloud((0, 0, 0, 1), (0, 0, 0), frame='odom'),
             topic=True, about='a pose in another frame than the map, then a cloud in its child frame'),
        Case('pose_stale_for_cloud', 'pose', False, pose_then_cloud((0, 0, 0, 1), (0, 0, 0), cloud_dt=30.0),
             topic=True, about='a valid pose, then a cloud 30 s later in its frame (beyond pose_tolerance)'),
        Case('pose_valid', 'pose', True, pose_then_cloud((0, 0, 0, 1), (0, 0, 0)), topic=True,
             about='a valid pose (identity), then a cloud in its frame'),
    ]
    return out


def fuzz_cases() -> list[Case]:
    """Every fuzz case, in the order they run (the map is restored after each that changed it)."""
    cases = cloud_cases() + pose_cases() + query_cases() + save_cases() + load_cases() + get_map_cases()
    names = [c.name for c in cases]
    assert len(names) == len(set(names)), 'duplicate fuzz case names'
    return cases


def run_fuzz(session: Session) -> dict:
    """Every fuzz case against the node; the map restored (or the node restarted) after each."""
    opts = session.opts
    assert session.client is not None
    folder = session.out / 'fuzz'
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    baseline = folder / 'baseline.npz'
    ensure_map(session)
    save_baseline(session, baseline)
    ctx = FuzzContext(session, folder, baseline)
    ref = baseline_answers(session, ctx)
    cases = [c for c in fuzz_cases() if not opts.cases or c.name in opts.cases]
    say(opts, f'fuzz: {len(cases)} cases against a map of {ref["facades"]} façades '
              f'(version {ref["version"]}); {int((ref["answers"]["facade"] >= 0).sum())} of '
              f'{len(ctx.probe)} probe points on a façade')
    results: dict[str, dict] = {}
    previous: dict | None = None
    for case in cases:
        if previous is not None and previous['dirty']:
            restore(session, ctx, ref, previous)  # the baseline back before the next case
        t = time.monotonic()
        results[case.name] = previous = run_case(session, ctx, case, ref)
        previous['seconds'] = round(time.monotonic() - t, 2)
        say(opts, f'fuzz {case.name}: {previous["outcome"]}'
                  f'{" (" + previous["detail"] + ")" if previous.get("detail") else ""}')
    passed = sum(r['passed'] for r in results.values())
    return {'cases': results, 'count': len(results), 'passed': passed, 'failed': len(results) - passed,
            'baseline': {'path': str(baseline), 'facades': ref['facades'], 'version': ref['version']},
            'restarts': sum(r['outcome'] == 'node died' for r in results.values())}


def ensure_map(session: Session) -> None:
    """A settled map with façades, of at most ``fuzz_map_points`` points (each case that
    changes the map costs a reload and a refit): the running node's, else a fresh node's
    fed the start of the drive."""
    opts = session.opts
    values = (session.wait_settled(opts.settle_timeout) or {}) if session.alive() else {}
    if values and 0 < (as_int(values, 'map_points') or 0) <= opts.fuzz_map_points and as_int(values, 'facades'):
        return
    if session.alive():
        say(opts, f'fuzz: a fresh node on a map of the drive\'s start (not the {as_int(values, "map_points")} '
                  f'points of the running one)')
    clouds = max(2, math.ceil(min(len(session.drive), opts.fuzz_map_points // 2) / opts.points))
    session.start_node(tag='fuzz')
    session.next_cloud = 0
    values = feed(session, clouds, opts.settle_timeout) or {}
    if not as_int(values, 'facades'):
        raise RuntimeError(f'no façades after {clouds} clouds of the drive: {values}')


def save_baseline(session: Session, baseline: Path) -> None:
    """Save the node's map as the baseline of the fuzz cases."""
    from uncertain_facade_map.srv import SaveMap

    assert session.client is not None
    response = session.client.call(SaveMap, 'save_map', SaveMap.Request(path=str(baseline)), 300.0)
    if response is None or not response.success:
        raise RuntimeError(f'the baseline could not be saved: {getattr(response, "message", "no answer")}')


def baseline_answers(session: Session, ctx: FuzzContext) -> dict:
    """The node's answers to the probe points and its map version, before any case."""
    from uncertain_facade_map.io.map_file import load_map

    answers, version, _ = session.query(ctx.probe)
    if answers is None:
        raise RuntimeError('the node does not answer query_points')
    return {'answers': answers, 'version': version, 'facades': len(load_map(ctx.baseline).facades)}


def map_probe(path: Path, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) query points: points of the map file's buildings with 0.3 m of noise."""
    from uncertain_facade_map.io.map_file import load_map

    fmap = load_map(path)
    rng = np.random.default_rng(seed)
    pts = np.vstack(list(fmap.points.values()))
    return pts[rng.choice(len(pts), n, replace=len(pts) < n)] + rng.normal(0.0, 0.3, (n, 3))


def wait_counted(session: Session, before: dict, after: float, timeout: float) -> dict | None:
    """Diagnostics in which one of the input counters moved since ``before``; None on timeout."""
    assert session.client is not None

    def moved(v: dict) -> bool:
        return any(as_int(v, k) != as_int(before, k) for k in INPUT_COUNTERS if k in v)

    return session.client.diagnostics(after=after, until=moved, timeout=timeout)


def counter_changes(before: dict, after: dict | None) -> dict:
    if not after:
        return {}
    keys = [k for k in after if k.startswith(('clouds_', 'points_', 'poses_', 'queries'))]
    return {k: as_int(after, k) - as_int(before, k) for k in keys
            if as_int(after, k) is not None and as_int(before, k) is not None and as_int(after, k) != as_int(before, k)}


def run_case(session: Session, ctx: FuzzContext, case: Case, ref: dict) -> dict:
    """One case: send it, wait for the node, check alive / answers / map; restore the map."""
    opts = session.opts
    assert session.client is not None and session.node is not None
    node = session.node
    offset = node.log_size()
    before = dict(session.client.diag_values)
    t = time.monotonic()
    result: dict[str, Any] = {'group': case.group, 'valid': case.valid, 'about': case.about}
    try:
        result.update(case.act(ctx))
    except Exception as exc:  # noqa: BLE001 - a case the client itself could not send
        result['client_error'] = f'{type(exc).__name__}: {exc}'[:300]
    after = None
    if case.topic and node.alive():
        after = wait_counted(session, before, t, opts.case_timeout)
        result['counted'] = after is not None
        if after is not None and not settled(after):
            after = session.wait_settled(opts.settle_timeout) or after
    if after is None:
        after = session.client.diagnostics(after=time.monotonic(), timeout=2.0 if node.alive() else 0.0)
    result['counters'] = counter_changes(before, after)
    answers, version, response = session.query(ctx.probe) if node.alive() else (None, None, None)
    result['alive'] = node.alive()
    if not result['alive']:
        result['exit_code'] = node.proc.returncode
    result['answered'] = answers is not None and result.get('answered', True)
    result['version'] = version
    result['unchanged'] = answers is not None and same_answers(answers, ref['answers']) and version == ref['version']
    log = node.log_since(offset)
    result['exception'] = exception_text(log)
    result['log'] = first_warning(log)
    if after and after.get('last_error') and after.get('last_error') != before.get('last_error'):
        result['last_error'] = after['last_error'][:300]
    classify(result, case)
    # Points handed to the worker may wait unseen (held back, or a failed update): reload anyway.
    took = any(result['counters'].get(k, 0) > 0 for k in ('clouds_in', 'clouds_mapped', 'clouds_failed',
                                                           'points_in', 'points_mapped'))
    result['dirty'] = not (result['alive'] and result['unchanged']) or took
    return result


def first_warning(log: str) -> str:
    for line in log.splitlines():
        if '[WARN]' in line or '[ERROR]' in line:
            return line.split(']: ', 1)[-1].strip()[:300]
    return ''


def classify(result: dict, case: Case) -> None:
    """outcome (handled, node died, map changed, no answer, valid ...) and passed."""
    if not result['alive']:
        result['outcome'] = 'node died'
    elif not result['answered']:
        result['outcome'] = 'no answer'
    elif not result['unchanged']:
        result['outcome'] = 'valid: map changed' if case.valid else 'map changed'
    else:
        result['outcome'] = 'valid: map unchanged' if case.valid else 'handled'
    result['passed'] = result['outcome'] in ('handled', 'valid: map changed', 'valid: map unchanged')
    notes = []
    if not case.valid and case.group in ('query', 'save', 'load') and result.get('success') and case.name != 'query_empty':
        notes.append('accepted')
    if result.get('tmp_left'):
        notes.append(f'tmp files left: {", ".join(result["tmp_left"])}')
    if case.topic and not result.get('counted', True):
        notes.append('no counter moved')
    detail = result.get('message') or result.get('log') or result.get('last_error') or ''
    result['detail'] = '; '.join([*notes, detail[:160]] if detail else notes)


def restore(session: Session, ctx: FuzzContext, ref: dict, result: dict) -> None:
    """Back to the baseline map: restart a dead node on it, reload a changed map."""
    from uncertain_facade_map.srv import LoadMap

    assert session.client is not None
    t = time.monotonic()
    if session.alive():
        session.client.call(LoadMap, 'load_map', LoadMap.Request(path=str(ctx.baseline)), 300.0)
        session.wait_settled(session.opts.settle_timeout)
        answers, version, _ = session.query(ctx.probe)
    else:
        answers = version = None
    if not same_answers(answers, ref['answers']):
        # Dead, or reloading did not give the baseline back (a stuck worker): start afresh on it.
        try:
            session.start_node(ctx.baseline, tag='fuzz_restart')
        except NodeDied as exc:
            result['restore_error'] = str(exc)[:300]
            raise
        answers, version, _ = session.query(ctx.probe)
        result['restarted_after'] = True
    ref['version'] = version
    result['restore_seconds'] = round(time.monotonic() - t, 2)


# ------------------------------------------------------------------------------------------
# Report
# ------------------------------------------------------------------------------------------
def summary(report: dict) -> dict:
    """The properties the issue asks for, each True/False (None: section not run)."""
    soak, kills, fuzz = report.get('soak'), report.get('kills'), report.get('fuzz')
    out: dict[str, Any] = {}
    if soak:
        acc = soak['accounting']
        out['soak_node_alive'] = soak['alive']
        out['soak_published_equals_received'] = acc['published_ok']
        out['soak_clouds_add_up'] = acc['clouds']['ok']
        out['soak_points_add_up'] = acc['points']['ok']
        out['soak_queries_answered'] = soak['queries']['failed'] == 0 and soak['queries']['calls'] > 0
    if kills:
        out.update({f'kills_{k}': v for k, v in kills['checks'].items()})
    if fuzz:
        out['fuzz_all_handled'] = fuzz['failed'] == 0
    return out


def table(report: dict) -> str:
    """The human-readable report."""
    lines = [f'Soak and fault suite, {report["started"]}; parameters {report["params"]}'
             + (f' with {" ".join(report["overrides"])}' if report['overrides'] else ''), '']
    if report.get('soak'):
        lines += [f'Fast DDS profile: {report.get("options", {}).get("dds_profile") or "none (Fast DDS defaults)"}',
                  '']
        lines += soak_table(report['soak'])
    if report.get('kills'):
        lines += kills_table(report['kills'])
    if report.get('fuzz'):
        lines += fuzz_table(report['fuzz'])
    lines += ['Summary (the properties of issue 13):']
    lines += [f'  {"PASS" if v else "FAIL"}  {k}' for k, v in report['summary'].items()]
    lines += ['', 'Section seconds: ' + ', '.join(f'{k} {v}' for k, v in report['seconds'].items())]
    return '\n'.join(lines) + '\n'


def soak_table(soak: dict) -> list[str]:
    s = soak['settings']
    lines = [f'Soak: {soak["published"]} clouds of {s["points"]:,} points at {s["rate"]} Hz '
             f'({soak["publish_seconds"]} s, max {soak["publish_late_max_s"]} s late), '
             f'drained in {soak["drain_seconds"]} s: {"yes" if soak["drained"] else "NO"}; node alive: {soak["alive"]}',
             f'{"t s":>6} {"RSS MB":>7} {"HWM MB":>7} {"queue":>5} {"publ.":>6} {"recv.":>6} {"mapped":>6} '
             f'{"dropped":>7} {"failed":>6} {"map pts":>9} {"stored":>9} {"update s":>8} {"cpu s":>6} {"lat. s":>7} '
             f'{"q p50ms":>7} {"q p95ms":>7}']
    for row in soak['samples']:
        c = row['counters']
        lines.append(f'{row["t"]:6.0f} {row["rss_mb"]:7.0f} {row["hwm_mb"]:7.0f} {_s(row["queue"]):>5} '
                     f'{row["published"]:6d} {_s(c.get("clouds_received", c.get("clouds_in"))):>6} '
                     f'{_s(c.get("clouds_mapped")):>6} {_s(c.get("clouds_dropped")):>7} {_s(c.get("clouds_failed")):>6} '
                     f'{_s(c.get("map_points")):>9} {_s(c.get("map_points_stored")):>9} '
                     f'{_s(c.get("last_update_seconds")):>8} {_s(c.get("last_update_cpu_seconds")):>6} '
                     f'{_s(c.get("latency_seconds")):>7} {_s(row["query"]["p50_ms"]):>7} {_s(row["query"]["p95_ms"]):>7}')
    lines += growth_table(soak['samples'])
    q = soak['queries']
    lines.append(f'query_points ({s["query_points"]} points every {s["query_period"]} s): {q["calls"]} calls, '
                 f'{q["failed"]} failed, p50 {q["p50_ms"]} ms, p95 {q["p95_ms"]} ms')
    a = soak['accounting']
    lines.append(f'accounting: published {a["published"]}, received {a["received_since_start"]} (lost {a["lost"]}, '
                 f'node\'s missed estimate {_s(a["missed_estimate"])}): {"ok" if a["published_ok"] else "FAIL"}')
    for kind in ('clouds', 'points'):
        k = a[kind]
        parts = ' + '.join(f'{p} {k[p]}' for p in (CLOUD_PARTS if kind == 'clouds' else POINT_PARTS))
        lines.append(f'  {kind}: received {_s(k["received"])} vs {parts} = {k["sum"]}: {"ok" if k["ok"] else "FAIL"}')
    if a['missing_keys']:
        lines.append(f'  keys the node does not publish (stand-ins used or 0): {", ".join(sorted(set(a["missing_keys"])))}')
    return [*lines, '']


#: Ranges of map points (stored and thinned) over which :func:`growth` takes medians.
GROWTH_RANGES = ((0, 0.5e6), (0.5e6, 1e6), (1e6, 2e6), (2e6, 3e6), (3e6, 4e6), (4e6, 5e6), (5e6, math.inf))


def growth(samples: list[dict]) -> list[dict]:
    """Per range of map points (:data:`GROWTH_RANGES`): the medians of the update's wall and
    CPU seconds (one value per update: samples that saw the same update count once), and the
    largest memory (RSS of all the node's processes) and stored points, with the memory per
    stored point above the first minute's."""
    updates: dict[tuple, tuple[float, float | None, float]] = {}
    for r in samples:
        c = r['counters']
        points, wall = as_int(c, 'map_points'), as_float(c, 'last_update_seconds')
        if points and wall:
            updates[(points, as_int(c, 'map_version'))] = (wall, as_float(c, 'last_update_cpu_seconds'), points)
    base = next((r for r in samples if r['t'] >= 60.0), None)
    out = []
    for lo, hi in GROWTH_RANGES:
        walls = [w for w, _, p in updates.values() if lo < p <= hi]
        cpus = [c for _, c, p in updates.values() if lo < p <= hi and c is not None]
        rows = [r for r in samples if lo < (as_int(r['counters'], 'map_points') or 0) <= hi]
        if not walls and not rows:
            continue
        rss = max((r['rss_mb'] for r in rows), default=math.nan)
        stored = max((as_int(r['counters'], 'map_points_stored') or 0 for r in rows), default=0)
        per_point = math.nan
        if base is not None and rows:
            b_stored = as_int(base['counters'], 'map_points_stored') or 0
            if stored > b_stored:
                per_point = (rss - base['rss_mb']) * 2**20 / (stored - b_stored)
        last = max(rows, key=lambda r: r['t'], default=None)
        parts = (last or {}).get('rss_parts_mb') or {}
        c = (last or {}).get('counters') or {}
        map_mb, facades_mb, published_mb = (as_float(c, k) for k in ('map_mb', 'facades_mb', 'published_mb'))
        other = (None if last is None or map_mb is None or facades_mb is None or published_mb is None
                 else round(last['rss_mb'] - map_mb - facades_mb - published_mb))
        out.append({'from': lo, 'to': hi, 'updates': len(walls), 'rss_parts_mb': parts, 'map_mb': map_mb,
                    'facades_mb': facades_mb, 'published_mb': published_mb, 'rss_less_map_mb': other,
                    'wall_median_s': round(float(np.median(walls)), 2) if walls else None,
                    'cpu_median_s': round(float(np.median(cpus)), 2) if cpus else None,
                    'rss_mb': round(rss), 'stored': stored,
                    'bytes_per_stored_point_after_1_min': None if math.isnan(per_point) else round(per_point)})
    return out


def growth_table(samples: list[dict]) -> list[str]:
    lines = ['Update time and memory by map points (medians over updates; memory: all the node\'s processes; '
             'bytes per stored point added after the first minute)',
             f'{"map points":>13} {"updates":>7} {"wall s":>7} {"cpu s":>6} {"RSS MB":>7} {"stored":>10} {"B/pt":>6} '
             f'{"map MB":>7} {"façades":>7} {"publ.":>6} {"rest MB":>7}   RSS MB by process at the range\'s last '
             f'sample',
             '  (map MB: the arrays of the map in the mapping process; façades: those of the node\'s copy of the '
             'façade models; publ.: the latest published maps, serialized; rest: RSS less these)']
    for g in growth(samples):
        hi = 'inf' if math.isinf(g['to']) else f'{g["to"] / 1e6:.1f}'
        lines.append(f'{g["from"] / 1e6:5.1f}-{hi:>4} M {g["updates"]:7d} {_s(g["wall_median_s"]):>7} '
                     f'{_s(g["cpu_median_s"]):>6} {g["rss_mb"]:7} {g["stored"]:10,d} '
                     f'{_s(g["bytes_per_stored_point_after_1_min"]):>6} {_s(g["map_mb"]):>7} '
                     f'{_s(g["facades_mb"]):>7} {_s(g["published_mb"]):>6} {_s(g["rss_less_map_mb"]):>7}   '
                     + ', '.join(f'{k} {v:.0f}' for k, v in g['rss_parts_mb'].items()))
    return lines


def kills_table(kills: dict) -> list[str]:
    c = kills['calibration']
    lines = [f'Kills: {len(kills["kills"])} SIGKILLs during save_map (a whole save {c["seconds"]} s, '
             f'its write {c["write_seconds"]} s); moments: '
             + ', '.join(f'{k} {v}' for k, v in kills['moments'].items()),
             f'{"#":>3} {"moment":<17} {"at share":>8} {"file":<8} {"restarted":<9} {"tmp after restart":<30} '
             f'{"answers =":<9} detail']
    for r in kills['kills']:
        lines.append(f'{r["index"] + 1:3d} {r["moment"]:<17} {r["fraction"]:8.2f} {r["file"]:<8} '
                     f'{str(r["restarted"]):<9} {(", ".join(r["tmp_after_restart"]) or "none")[:30]:<30} '
                     f'{str(r["answers_identical"]):<9} {r.get("exception") or r["file_detail"]}')
    lines.append('checks: ' + ', '.join(f'{k} {"ok" if v else "FAIL"}' for k, v in kills['checks'].items()))
    return [*lines, '']


def fuzz_table(fuzz: dict) -> list[str]:
    lines = [f'Fuzz: {fuzz["count"]} cases, {fuzz["passed"]} passed, {fuzz["failed"]} failed '
             f'({fuzz["restarts"]} node restarts)',
             f'{"case":<28} {"group":<7} {"input":<5} {"outcome":<20} {"ok":<4} detail / exception']
    for name, r in fuzz['cases'].items():
        detail = r.get('exception') or r.get('detail') or ''
        lines.append(f'{name:<28} {r["group"]:<7} {"valid" if r["valid"] else "bad":<5} {r["outcome"]:<20} '
                     f'{"ok" if r["passed"] else "FAIL":<4} {detail[:110]}')
    return [*lines, '']


def _s(value: Any) -> str:
    return '-' if value is None else str(value)


def plot(report: dict, path: Path) -> Path | None:
    """soak.png: memory, map points, queue, update latency, query latency and clouds over time."""
    soak = report.get('soak')
    if not soak or not soak['samples']:
        return None
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    rows = soak['samples']
    t = [r['t'] for r in rows]

    def series(key: str) -> list[float]:
        return [float(r['counters'][key]) if key in r['counters'] else math.nan for r in rows]

    fig, ax = plt.subplots(2, 3, figsize=(15, 8), constrained_layout=True)
    ax[0, 0].plot(t, [r['rss_mb'] for r in rows], label='RSS')
    ax[0, 0].plot(t, [r['hwm_mb'] for r in rows], '--', label='peak (HWM)')
    ax[0, 0].set(title='node memory', ylabel='MB')
    ax[0, 1].plot(t, series('map_points'), label='mapped')
    ax[0, 1].plot(t, series('map_points_stored'), label='stored')
    ax[0, 1].set(title='map points', ylabel='points')
    ax[0, 2].plot(t, [r['queue'] if r['queue'] is not None else math.nan for r in rows])
    ax[0, 2].set(title='clouds waiting (queue)', ylabel='clouds')
    ax[1, 0].plot(t, series('last_update_seconds'), label='last update')
    ax[1, 0].plot(t, series('last_update_cpu_seconds'), label='its CPU time')
    ax[1, 0].plot(t, series('latency_seconds'), label='arrival to map')
    ax[1, 0].set(title='update latency', ylabel='s')
    ax[1, 1].plot(t, [r['query']['p50_ms'] if r['query']['p50_ms'] is not None else math.nan for r in rows],
                  label='p50')
    ax[1, 1].plot(t, [r['query']['p95_ms'] if r['query']['p95_ms'] is not None else math.nan for r in rows],
                  label='p95')
    ax[1, 1].set(title='query_points latency', ylabel='ms')
    ax[1, 2].plot(t, [r['published'] for r in rows], label='published')
    for key in ('clouds_received', 'clouds_in', 'clouds_mapped', 'clouds_dropped'):
        if any(key in r['counters'] for r in rows):
            ax[1, 2].plot(t, series(key), label=key)
    ax[1, 2].set(title='clouds', ylabel='clouds')
    for a in ax.flat:
        a.set_xlabel('s since the start')
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=8)
        a.grid(alpha=0.3)
    fig.suptitle(f'soak: {soak["settings"]["rate"]} Hz x {soak["settings"]["points"]:,} points')
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_report(report: dict, out: Path) -> dict:
    """report.json, report.txt and soak.png in ``out``; returns the paths."""
    out.mkdir(parents=True, exist_ok=True)
    (out / 'report.json').write_text(json.dumps(report, indent=1, default=_jsonable))
    (out / 'report.txt').write_text(table(report))
    png = plot(report, out / 'soak.png')
    return {'json': str(out / 'report.json'), 'table': str(out / 'report.txt'), 'png': str(png) if png else None}


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


# ------------------------------------------------------------------------------------------
# Main
# ------------------------------------------------------------------------------------------
def run(opts: Options) -> dict:
    """Run the sections; returns the report (also written to ``opts.out``)."""
    session = Session(opts)
    report: dict[str, Any] = {'started': time.strftime('%Y-%m-%d %H:%M:%S'), 'params': str(opts.params),
                              'overrides': list(opts.overrides), 'options': dataclasses.asdict(opts),
                              'seconds': {}, 'errors': {}}
    sections = {'soak': run_soak, 'kills': run_kills, 'fuzz': run_fuzz}
    t_all = time.monotonic()
    try:
        session.open()
        report['seconds']['set-up'] = round(time.monotonic() - t_all, 1)
        for name in SECTIONS:
            if name not in opts.sections:
                continue
            t = time.monotonic()
            try:
                report[name] = sections[name](session)
            except (NodeDied, RuntimeError, TimeoutError, OSError) as exc:
                report['errors'][name] = f'{type(exc).__name__}: {exc}'[:1000]
                say(opts, f'{name}: stopped: {report["errors"][name]}')
            report['seconds'][name] = round(time.monotonic() - t, 1)
    finally:
        session.close()
    report['seconds']['total'] = round(time.monotonic() - t_all, 1)
    report['node_start_seconds'] = [round(s, 1) for s in session.start_seconds]
    report['summary'] = summary(report)
    report['files'] = write_report(report, Path(opts.out))
    return report


def main(argv: list[str] | None = None) -> int:
    opts = parse_args(argv)
    report = run(opts)
    print(Path(report['files']['table']).read_text())
    print(f'report: {report["files"]["json"]}, {report["files"]["table"]}, {report["files"]["png"]}')
    return 0 if all(report['summary'].values()) and not report['errors'] else 1


if __name__ == '__main__':
    raise SystemExit(main())
