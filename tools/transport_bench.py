"""Camera images between two processes over Fast DDS, with and without the shared-memory profile.

A publisher process sends 640x480 rgb8 ``sensor_msgs/Image`` frames at a fixed rate to a
subscriber process (own ``ROS_DOMAIN_ID``, localhost discovery), once with Fast DDS's built-in
transports and once with ``config/fastdds_shm.xml`` (an 8 MiB shared-memory segment), each with
sensor-data (best effort) and reliable QoS. Reported per run: frames sent and received, received
rate, loss, latency from the header stamp to the subscriber callback (median and 95th
percentile), the time one ``publish()`` call takes, the Fast DDS shared-memory segments the
subscriber had mapped (its own, plus the publisher's when data came through shared memory) and
the bytes that crossed the loopback interface per frame sent (all processes on the machine:
about one frame's size when the frames travel over UDP, near zero over shared memory).

Usage: ``python -m tools.transport_bench [--duration S] [--rate HZ] ...``;
``main(argv)`` returns the Markdown section for ``make bench``.
"""
from __future__ import annotations

import argparse
import array
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

IMAGE_TOPIC = '/bench/image'
READY_TOPIC = '/bench/ready'
DONE_TOPIC = '/bench/done'
PROFILE_NAME = 'fastdds_shm.xml'
#: The repository root: the children run ``-m tools.transport_bench`` from it.
REPO = Path(__file__).resolve().parents[1]
PROFILE_ENV_VARS = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
QOS_CHOICES = ('sensor_data', 'reliable')


def profile_path() -> Path:
    """Path of the shipped Fast DDS profile: the installed share directory, else the sources.

    Returns
    -------
    Path
        ``share/calibration_bringup/config/fastdds_shm.xml`` when the package is installed
        (colcon or ``make setup``), otherwise the one in the package's sources.
    """
    try:
        from ament_index_python.packages import get_package_share_directory
        installed = Path(get_package_share_directory('calibration_bringup')) / 'config' / PROFILE_NAME
        if installed.is_file():
            return installed
    except (ImportError, LookupError, ValueError, OSError):  # not installed, or no prefix path
        pass
    return REPO / 'ros2_ws' / 'src' / 'calibration_bringup' / 'config' / PROFILE_NAME


# For comparison only: what the frames cost when shared memory is off and they go over UDP.
UDP_ONLY_PROFILE = """<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <transport_descriptors>
      <transport_descriptor><transport_id>udp</transport_id><type>UDPv4</type></transport_descriptor>
    </transport_descriptors>
    <participant profile_name="udp_only" is_default_profile="true">
      <rtps>
        <userTransports><transport_id>udp</transport_id></userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
  </profiles>
</dds>
"""
PROFILE_LABELS = {'default': 'Fast DDS default', 'shm': 'fastdds_shm.xml (SHM 8 MiB + UDP)',
                  'udp': 'UDPv4 only (subnet discovery)'}


def profile_env(profile: Path | None, base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment for a ROS process that uses ``profile`` (or Fast DDS defaults when None).

    Parameters
    ----------
    profile : Path or None
        Fast DDS XML profile; None removes any inherited profile variables.
    base : dict, optional
        Environment to start from (default: ``os.environ``).

    Returns
    -------
    dict[str, str]
        A copy with both profile variables set (Fast DDS 2.x and 3.x names) or removed.
    """
    env = dict(os.environ if base is None else base)
    for var in PROFILE_ENV_VARS:
        env.pop(var, None)
        if profile is not None:
            env[var] = str(profile)
    return env


def _qos(kind: str) -> Any:
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    if kind == 'sensor_data':
        return qos_profile_sensor_data  # best effort, keep last 5
    if kind == 'reliable':
        return QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    raise ValueError(f'unknown QoS {kind!r}; expected one of {QOS_CHOICES}')


def _latched_qos() -> Any:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def shm_segments() -> dict[str, int]:
    """Fast DDS shared-memory segments this process has mapped, with their mapped sizes.

    Returns
    -------
    dict[str, int]
        ``/dev/shm/fastrtps_<id>`` -> bytes mapped; port queues and lock files are left out.
    """
    sizes: dict[str, int] = {}
    with open('/proc/self/maps') as maps:
        for line in maps:
            fields = line.split()
            if len(fields) < 6 or not fields[5].startswith('/dev/shm/fastrtps_'):
                continue
            name = fields[5]
            if '_port' in name or name.endswith('_el'):
                continue
            lo, hi = (int(x, 16) for x in fields[0].split('-'))
            sizes[name] = sizes.get(name, 0) + hi - lo
    return sizes


def loopback_bytes() -> int:
    """Bytes received so far on the loopback interface (``/proc/net/dev``; 0 if unknown)."""
    try:
        for line in Path('/proc/net/dev').read_text().splitlines():
            name, _, rest = line.partition(':')
            if name.strip() == 'lo':
                return int(rest.split()[0])
    except OSError:
        pass
    return 0


def _spin_until(executor: Any, cond: Any, deadline: float) -> bool:
    while time.monotonic() < deadline:
        if cond():
            return True
        executor.spin_once(timeout_sec=0.02)
    return bool(cond())


def run_subscriber(args: argparse.Namespace) -> dict[str, Any]:
    """Subscriber role: receive until the publisher's count arrives, then report.

    Parameters
    ----------
    args : argparse.Namespace
        ``qos`` and ``timeout`` (seconds).

    Returns
    -------
    dict
        Per-frame records ``[receive_wall, stamp, seq, nbytes, first_byte, last_byte]``,
        ``sent`` (the publisher's count, None if it never arrived) and ``shm`` segments.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image
    from std_msgs.msg import UInt32

    rclpy.init()
    node = rclpy.create_node('transport_bench_sub')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    records: list[list[float]] = []
    done: dict[str, float] = {}
    mapped: dict[str, int] = {}

    def on_image(msg: Image) -> None:
        now = time.time()
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        data = msg.data
        records.append([now, stamp, int(msg.header.frame_id), len(data), data[0], data[-1]])
        if len(records) == 1:
            # Sampled while the publisher is surely alive: a segment it created and this
            # process mapped shows that traffic reached us through shared memory.
            mapped.update(shm_segments())

    def on_done(msg: UInt32) -> None:
        done.setdefault('sent', msg.data)
        done.setdefault('at', time.monotonic())

    node.create_subscription(Image, IMAGE_TOPIC, on_image, _qos(args.qos))
    node.create_subscription(UInt32, DONE_TOPIC, on_done, _latched_qos())
    ready = node.create_publisher(UInt32, READY_TOPIC, _latched_qos())
    deadline = time.monotonic() + args.timeout
    # Tell the publisher to start only once this side has discovered its writer, so the first
    # best-effort frames are not lost to one-sided discovery.
    _spin_until(executor, lambda: node.count_publishers(IMAGE_TOPIC) > 0, deadline)
    ready.publish(UInt32(data=1))
    # Frames sent before the count may still be in flight: wait for them, 1 s at most.
    _spin_until(executor, lambda: 'sent' in done and (
        len(records) >= done['sent'] or time.monotonic() - done['at'] > 1.0), deadline)
    mapped.update(shm_segments())
    result = {'records': records, 'sent': done.get('sent'), 'shm': mapped}
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown()
    return result


def run_publisher(args: argparse.Namespace) -> dict[str, Any]:
    """Publisher role: wait for the subscriber, publish ``rate * duration`` frames, report.

    Parameters
    ----------
    args : argparse.Namespace
        ``qos``, ``rate`` (Hz), ``duration`` (s), ``width``, ``height`` and ``timeout`` (s).

    Returns
    -------
    dict
        ``sent``, ``publish_s`` (duration of each ``publish()`` call), ``elapsed`` and ``shm``.
    """
    import rclpy
    from rclpy.duration import Duration
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image
    from std_msgs.msg import UInt32

    rclpy.init()
    node = rclpy.create_node('transport_bench_pub')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    image_pub = node.create_publisher(Image, IMAGE_TOPIC, _qos(args.qos))
    done_pub = node.create_publisher(UInt32, DONE_TOPIC, _latched_qos())
    ready: list[int] = []
    node.create_subscription(UInt32, READY_TOPIC, lambda m: ready.append(m.data), _latched_qos())
    deadline = time.monotonic() + args.timeout
    if not _spin_until(executor, lambda: ready and image_pub.get_subscription_count() > 0,
                       deadline):
        raise TimeoutError('the subscriber was not discovered')

    msg = Image(height=args.height, width=args.width, encoding='rgb8', is_bigendian=0,
                step=3 * args.width)
    # One buffer, edited in place: marking bytes per frame lets the subscriber check content
    # without copying 900 kB in Python for every frame.
    msg.data = array.array('B', bytes(3 * args.width * args.height))
    data = msg.data  # the setter may copy: edit the array the message holds
    count = max(1, int(round(args.rate * args.duration)))
    period = 1.0 / args.rate
    publish_s: list[float] = []
    start = time.monotonic()
    for seq in range(count):
        delay = start + seq * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)  # the publishing schedule, not a wait on a condition
        data[0], data[-1] = seq % 256, (7 * seq) % 256
        msg.header.frame_id = str(seq)
        now = time.time_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now, 1_000_000_000)
        t0 = time.perf_counter()
        image_pub.publish(msg)
        publish_s.append(time.perf_counter() - t0)
    elapsed = time.monotonic() - start
    if args.qos == 'reliable':
        image_pub.wait_for_all_acked(Duration(seconds=10))
    done_pub.publish(UInt32(data=count))
    done_pub.wait_for_all_acked(Duration(seconds=10))
    result = {'sent': count, 'publish_s': publish_s, 'elapsed': elapsed, 'shm': shm_segments()}
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown()
    return result


def _last_json(text: str) -> dict[str, Any]:
    for line in reversed(text.strip().splitlines()):
        if line.startswith('{'):
            return json.loads(line)
    raise ValueError('no JSON result line')


def run_pair(profile: Path | None, label: str, qos: str, *, domain_id: int,
             discovery_range: str = 'LOCALHOST', rate: float = 30.0, duration: float = 5.0,
             width: int = 640, height: int = 480, timeout: float = 60.0) -> dict[str, Any]:
    """Run one publisher process and one subscriber process and summarise the transfer.

    Parameters
    ----------
    profile : Path or None
        Fast DDS profile for both processes, None for Fast DDS defaults.
    label : str
        Name of the configuration in the results.
    qos : {'sensor_data', 'reliable'}
        QoS of the image topic.
    domain_id : int
        ROS domain for this pair only.
    discovery_range : str
        ``ROS_AUTOMATIC_DISCOVERY_RANGE``. With ``LOCALHOST``, rmw_fastrtps appends its own
        localhost UDPv4 and default shared-memory transports to the profile's; ``SUBNET`` (with
        127.0.0.1 as static peer) leaves the profile's transports alone.
    rate, duration : float
        Publishing rate [Hz] and length [s].
    width, height : int
        Image size (rgb8).
    timeout : float
        Deadline for each process [s]; both are killed past it.

    Returns
    -------
    dict
        ``sent``, ``received``, ``rate_hz``, ``loss``, ``latency_ms`` (median, p95),
        ``publish_ms`` (median), ``content_ok``, ``sub_shm`` (segment sizes mapped by the
        subscriber), ``loopback_bytes_per_frame`` (per frame sent), ``data_path`` ('UDP' or
        'SHM', inferred from the loopback bytes) and the raw ``records``.
    """
    env = profile_env(profile)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = discovery_range
    if discovery_range == 'SUBNET':
        env['ROS_STATIC_PEERS'] = '127.0.0.1'  # discovery without relying on multicast
    env['RMW_IMPLEMENTATION'] = 'rmw_fastrtps_cpp'
    # The children import this module by name from the repository root (tools/ is not installed).
    pkg_parent = str(REPO)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (pkg_parent, env.get('PYTHONPATH')) if p)
    common = ['--qos', qos, '--rate', str(rate), '--duration', str(duration), '--width',
              str(width), '--height', str(height), '--timeout', str(timeout)]
    cmd = [sys.executable, '-m', 'tools.transport_bench']
    lo_before = loopback_bytes()
    procs = [subprocess.Popen(cmd + ['--role', role] + common, env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for role in ('sub', 'pub')]
    outputs = []
    try:
        for proc in procs:
            out, err = proc.communicate(timeout=timeout + 30.0)
            if proc.returncode != 0:
                raise RuntimeError(f'{proc.args[-len(common) - 1]} process failed '
                                   f'({proc.returncode}):\n{err[-3000:]}')
            outputs.append(_last_json(out))
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    lo_delta = loopback_bytes() - lo_before
    sub, pub = outputs
    records = sub['records']
    frame_bytes = 3 * width * height
    received = len(records)
    latencies = sorted(1e3 * (r[0] - r[1]) for r in records)
    content_ok = all(r[3] == frame_bytes and r[4] == r[2] % 256 and r[5] == (7 * r[2]) % 256
                     for r in records)
    span = records[-1][0] - records[0][0] if received > 1 else 0.0
    return {
        'profile': label,
        'qos': qos,
        'discovery_range': discovery_range,
        'sent': pub['sent'],
        'received': received,
        'rate_hz': (received - 1) / span if span > 0 else 0.0,
        'loss': 1.0 - received / pub['sent'],
        'latency_ms': (statistics.median(latencies) if latencies else float('nan'),
                       latencies[int(0.95 * (len(latencies) - 1))] if latencies else float('nan')),
        'publish_ms': 1e3 * statistics.median(pub['publish_s']),
        'content_ok': content_ok,
        'sub_shm': sub['shm'],
        'pub_shm': pub['shm'],
        'loopback_bytes_per_frame': lo_delta / max(pub['sent'], 1),
        # Every frame sent over UDP crosses `lo` at least once; far less means shared memory.
        'data_path': 'UDP' if lo_delta > 0.5 * frame_bytes * pub['sent'] else 'SHM',
        'records': records,
    }


def format_table(results: list[dict[str, Any]], *, rate: float, duration: float, width: int,
                 height: int) -> str:
    """Markdown section for ``make bench`` from :func:`run_pair` results."""
    lines = [
        '## calibration_bringup: image transport between processes (Fast DDS)',
        '',
        f'{width}x{height} rgb8 `sensor_msgs/Image` ({3 * width * height:,} bytes of pixels) at '
        f'{rate:g} Hz for {duration:g} s, publisher and subscriber in separate processes, '
        'localhost discovery (the UDP-only row uses subnet discovery with 127.0.0.1 as static peer: '
        'under localhost discovery rmw_fastrtps adds a default shared-memory transport of its own). '
        'Intact: every received frame has its full size and the bytes marked by the publisher. '
        'Latency: header stamp to subscriber callback. Loopback: bytes on `lo` (whole machine) per '
        'sent frame; the data path is inferred from it (UDP moves at least one frame over `lo` per '
        'frame sent). SHM segments: Fast DDS shared-memory segments the subscriber had mapped (its '
        'own and the publisher\'s).',
        '',
        '| profile | QoS | sent | received | intact | rate [Hz] | loss | latency median / p95 [ms] '
        '| publish() [ms] | loopback [kB/frame] | data path | SHM segments [MiB] |',
        '|---|---|---|---|---|---|---|---|---|---|---|---|',
    ]
    for r in results:
        segs = ', '.join(f'{s / 2**20:.1f}' for s in sorted(r['sub_shm'].values(), reverse=True))
        lines.append(
            f"| {r['profile']} | {r['qos']} | {r['sent']} | {r['received']} "
            f"| {'yes' if r['content_ok'] else 'NO'} | {r['rate_hz']:.1f} "
            f"| {100 * r['loss']:.1f}% | {r['latency_ms'][0]:.1f} / {r['latency_ms'][1]:.1f} "
            f"| {r['publish_ms']:.2f} | {r['loopback_bytes_per_frame'] / 1e3:.0f} "
            f"| {r['data_path']} | {segs or '-'} |")
    return '\n'.join(lines) + '\n'


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='python -m tools.transport_bench',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--role', choices=('sub', 'pub'), help=argparse.SUPPRESS)
    p.add_argument('--qos', choices=QOS_CHOICES, action='append',
                   help='QoS of the image topic (repeatable; default: both)')
    p.add_argument('--profile', choices=tuple(PROFILE_LABELS), action='append',
                   help='Fast DDS configuration (repeatable; default: all): Fast DDS defaults, '
                        'the shipped fastdds_shm.xml, or UDPv4 only for comparison')
    p.add_argument('--rate', type=float, default=30.0, help='frames per second (30)')
    p.add_argument('--duration', type=float, default=5.0, help='seconds of publishing (5)')
    p.add_argument('--width', type=int, default=640)
    p.add_argument('--height', type=int, default=480)
    p.add_argument('--timeout', type=float, default=60.0, help='deadline per process [s]')
    p.add_argument('--domain-id', type=int, default=None,
                   help='first ROS domain id (default: 150 + pid %% 60); each run takes the next')
    return p


def main(argv: list[str] | None = None) -> str:
    """Run every (profile, QoS) combination and return the Markdown table.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments (default ``sys.argv[1:]``).

    Returns
    -------
    str
        The Markdown section (the child roles print a JSON line instead and return it).
    """
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    if args.role is not None:
        args.qos = (args.qos or ['sensor_data'])[0]
        result = run_subscriber(args) if args.role == 'sub' else run_publisher(args)
        return json.dumps(result)
    profiles = args.profile or list(PROFILE_LABELS)
    qoses = args.qos or list(QOS_CHOICES)
    # Domains 150..229 stay clear of the test fixture's 1..100 and of Fast DDS's port limit.
    domain = args.domain_id if args.domain_id is not None else 150 + os.getpid() % 60
    results = []
    with tempfile.TemporaryDirectory(prefix='transport_bench_') as tmp:
        udp_only = Path(tmp) / 'udp_only.xml'
        udp_only.write_text(UDP_ONLY_PROFILE)
        files = {'default': None, 'shm': profile_path(), 'udp': udp_only}
        for prof in profiles:
            for qos in qoses:
                # Under LOCALHOST discovery rmw_fastrtps adds a shared-memory transport of its
                # own, so the UDP-only comparison needs the subnet range to stay UDP-only.
                results.append(run_pair(files[prof], PROFILE_LABELS[prof], qos, domain_id=domain,
                                        discovery_range='SUBNET' if prof == 'udp' else 'LOCALHOST',
                                        rate=args.rate, duration=args.duration, width=args.width,
                                        height=args.height, timeout=args.timeout))
                domain += 1
    return format_table(results, rate=args.rate, duration=args.duration, width=args.width,
                        height=args.height)


if __name__ == '__main__':
    print(main(), flush=True)
