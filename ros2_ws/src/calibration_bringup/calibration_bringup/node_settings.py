"""Parameters of the recorder and bag player nodes, one field each (pure; no rclpy).

Each field's default, description and range is the node's parameter
(:func:`calibration_interfaces.node_util.declare_settings`); ``config/recorder.yaml`` overrides
what a calibration run needs.
"""
from __future__ import annotations

from dataclasses import dataclass

from calibration_interfaces.contract import CONTRACT, IMAGE_TOPICS, RECORD_DEPTH
from calibration_interfaces.parameters import setting

from .mcap_writer import COMPRESSIONS

__all__ = ['RecorderSettings', 'PlayerSettings']


@dataclass(frozen=True)
class RecorderSettings:
    """Parameters of ``recorder_node`` (node name ``mcap_recorder``)."""

    output: str = setting('', "Path of the .mcap file; '' = recording_<YYYYmmdd-HHMMSS>.mcap here")
    overwrite: bool = setting(True, 'Replace an existing output file (false: refuse)')
    topics: tuple[str, ...] = setting(tuple(t.name for t in CONTRACT),
                                      'Topics to record (default: the topic contract); others: type discovered')
    exclude: tuple[str, ...] = setting((), 'Topics left out')
    exclude_images: bool = setting(False, 'Leave out ' + ', '.join(IMAGE_TOPICS))
    compression: str = setting('zstd', 'Chunk compression', choices=COMPRESSIONS)
    chunk_size: int = setting(1 << 20, 'Uncompressed bytes per chunk (a SIGKILL loses at most one)',
                              (4096, 1 << 28))
    flush_period: float = setting(1.0, 'Write a partial chunk after this long [s] (0: only full chunks)',
                                  (0.0, 3600.0))
    discovery_period: float = setting(0.5, 'Period of the check for new publishers [s]', (0.01, 60.0))
    queue_depth: int = setting(100, 'Subscription queue depth (keep last) of best-effort topics (images)', (1, 100000))
    reliable_queue_depth: int = setting(RECORD_DEPTH, 'Subscription queue depth (keep last) of reliable topics: what '
                                                      'waits while the recorder is busy is recorded late, not lost',
                                        (1, 100000))
    record_tf: bool = setting(True, 'Also write /tf and /tf_static, derived from /joint_states, /body_schema/true, '
                                    '/body_schema/estimate and the camera poses (tf_recording.py)')
    robot: str = setting('icub_right_arm', 'Robot description of the TF frames: packaged name or YAML path')


@dataclass(frozen=True)
class PlayerSettings:
    """Parameters of ``bag_player``."""

    bag: str = setting('', 'The .mcap file to play')
    rate: float = setting(1.0, 'Speed factor (0 = as fast as possible)', (0.0, 1000.0))
    topics: tuple[str, ...] = setting((), 'Topics to play (empty: all)')
    publish_clock: bool = setting(True, 'Publish /clock from the log times (the recorded /clock is then not played)')
    clock_rate: float = setting(100.0, '/clock frequency [Hz]', (0.1, 10000.0))
    loop: bool = setting(False, 'Start again at the end of the bag')
    start_offset: float = setting(0.0, 'Skip the first seconds of the bag [s]', (0.0, 1e9))
    delay: float = setting(0.0, 'Wall time to wait before playing [s]', (0.0, 3600.0))
    start_paused: bool = setting(False, 'Wait for ~/resume before playing')
