"""Parameters of ``viz_node`` (node name ``calibration_viz``), one field each (pure; no rclpy)."""
from __future__ import annotations

from dataclasses import dataclass

from calibration_interfaces.contract import IMAGE_TRANSPORTS
from calibration_interfaces.parameters import setting

__all__ = ['VizSettings']


@dataclass(frozen=True)
class VizSettings:
    """Parameters of ``viz_node``; ``config/viz.yaml`` sets a run's values."""

    robot: str = setting('icub_right_arm', 'Robot description: packaged name or YAML path')
    host: str = setting('127.0.0.1', "Interface the web server listens on ('0.0.0.0': every one)")
    port: int = setting(8080, 'HTTP and WebSocket port of the view', (1, 65535))
    redraw_rate: float = setting(10.0, 'Most redraws per wall second (only when something changed) [Hz]',
                                 (0.1, 60.0))
    image_rate: float = setting(2.0, 'Most camera images shown per wall second and eye (0: none) [Hz]',
                                (0.0, 30.0))
    history: int = setting(50, 'Observed hand poses drawn (the latest)', (1, 10000))
    error_configs: int = setting(200, 'Configurations of the error curve (the offline evaluation: 1000)',
                                 (10, 5000))
    cameras: tuple[str, ...] = setting(('left', 'right'), 'Eyes whose camera is drawn')
    transport: str = setting('raw', 'Image transport: raw (image_raw) or compressed (image_raw/compressed)',
                             choices=IMAGE_TRANSPORTS)
