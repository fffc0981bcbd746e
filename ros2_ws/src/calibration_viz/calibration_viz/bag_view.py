"""A recorded calibration in a 3D panel layout: the bag opened in the Rerun viewer.

Rerun's own MCAP importer (the one ``rerun calibration.mcap`` uses) reads what the recorder
writes: ``/tf`` and ``/tf_static`` become the frame tree, ``/robot_description`` the real arm's
meshes, the eye images and ``camera_info`` pinhole cameras. This module adds what a generic viewer
cannot know: the estimated arm (the last ``/body_schema/robot_description``, links under
``estimate/``, drawn on the bag's ``estimate/`` frames, so the ghost moves with every estimate),
the observed hand poses with their 3-sigma covariance ellipsoids, the error curve from the
``metrics.csv`` that ``evaluate`` writes beside the bag, and a layout (a blueprint): the 3D scene,
both eyes, the error curve.

Why Rerun for bags (the live view is viser): it opens ROS 2 MCAP files itself, so this is a layout
over the user's own bag rather than a second copy of it, and its viewer runs natively or in the
browser (``rerun-sdk`` bundles both). The Foxglove app would read the same bag, but it is not
installable from the package registries here.

Usage::

    python -m calibration_viz.bag_view results/demo/calibration.mcap            # serve, print URL
    python -m calibration_viz.bag_view BAG --save view.rrd                        # rerun view.rrd
    python -m calibration_viz.bag_view BAG --screenshot docs/bag_view.png         # headless Chromium
"""
from __future__ import annotations

import argparse
import csv
import os
import signal
import socket
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from calibration_interfaces.contract import ESTIMATE_FRAME_PREFIX
from calibration_interfaces.mcap_reader import BagError, read_messages, recover, summary
from calibration_viz.scene import covariance_ellipsoid

__all__ = ['Observations', 'estimate_urdf', 'hand_observations', 'error_curve', 'blueprint', 'log_bag', 'main']

ROOT_FRAME = 'root_link'
ESTIMATE_ENTITY = 'estimate_arm'
OBSERVATION_ENTITY = 'observations/hand_pose'
ERROR_ENTITY = 'errors'
#: The timeline Rerun's MCAP importer creates from the messages' log times.
LOG_TIMELINE = 'message_log_time'


class Observations(NamedTuple):
    """Observed hand poses with their position uncertainty (N observations)."""

    log_time_ns: NDArray[np.int64]   #: (N,) when each was recorded [ns]
    centers: NDArray[np.float64]     #: (N, 3) hand positions in ``frame`` [m]
    half_sizes: NDArray[np.float64]  #: (N, 3) 3-sigma semi-axes [m]
    quaternions: NDArray[np.float64]  #: (N, 4) ellipsoid orientations, xyzw
    frame: str                       #: the poses' ``header.frame_id``


def estimate_urdf(bag: str | Path) -> str | None:
    """The last URDF of the estimated arm in ``bag``, or None if the estimator published none."""
    text = None
    for _, _, msg in read_messages(bag, ['/body_schema/robot_description']):
        text = msg.data
    return text


def hand_observations(bag: str | Path, n_sigma: float = 3.0) -> Observations:
    """The ``/hand_pose`` observations of ``bag`` as ellipsoids (positions and their covariance)."""
    times, centers, half, quats = [], [], [], []
    frame = ROOT_FRAME
    for _, t, msg in read_messages(bag, ['/hand_pose']):
        p = msg.pose.pose.position
        try:
            radii, rot = covariance_ellipsoid(np.asarray(msg.pose.covariance, dtype=float), n_sigma)
        except ValueError:
            continue  # a non-finite covariance has no ellipsoid; the estimator rejected it too
        times.append(t)
        centers.append((p.x, p.y, p.z))
        half.append(radii)
        quats.append(Rotation.from_matrix(rot).as_quat())
        frame = msg.header.frame_id or frame
    return Observations(np.asarray(times, dtype=np.int64), np.asarray(centers, dtype=float).reshape(-1, 3),
                        np.asarray(half, dtype=float).reshape(-1, 3), np.asarray(quats, dtype=float).reshape(-1, 4),
                        frame)


def error_curve(metrics_csv: str | Path) -> dict[str, NDArray[np.float64]]:
    """Columns ``sim_time``, ``position_mm``, ``orientation_deg`` of ``evaluate``'s metrics.csv.

    Raises
    ------
    ValueError
        If a column is missing (the file is not ``evaluate``'s).
    """
    with open(metrics_csv, newline='') as f:
        rows = list(csv.DictReader(f))
    cols = ('sim_time', 'position_mm', 'orientation_deg')
    missing = [c for c in cols if rows and c not in rows[0]]
    if missing:
        raise ValueError(f'{metrics_csv}: no column(s) {missing}; is it the metrics.csv evaluate writes?')
    return {c: np.array([float(r[c]) for r in rows]) for c in cols}


def blueprint() -> 'rrb.Blueprint':  # noqa: F821 (rerun is imported lazily)
    """The layout: the 3D scene on the left; the eyes and the error curve on the right."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name='arm, estimate and observations', origin='/',
                              contents=['/**', '- /camera/**/image_raw', '- /camera/**/image_raw/compressed',
                                        f'- /{ERROR_ENTITY}/**']),
            rrb.Vertical(
                rrb.Horizontal(rrb.Spatial2DView(name='left eye', origin='/camera/left/image_raw'),
                               rrb.Spatial2DView(name='right eye', origin='/camera/right/image_raw')),
                rrb.TimeSeriesView(name='hand error (evaluate)', origin=f'/{ERROR_ENTITY}'),
                row_shares=[1, 1]),
            column_shares=[3, 2]),
        rrb.SelectionPanel(state='collapsed'), rrb.BlueprintPanel(state='collapsed'),
        # Following: the view opens at the end of the run (the last estimate), not at its start.
        rrb.TimePanel(state='collapsed', timeline=LOG_TIMELINE, play_state='following'),
        collapse_panels=False)


def log_bag(bag: str | Path, metrics_csv: str | Path | None = None, history: int = 50) -> None:
    """Log ``bag`` and the calibration's extras to the current Rerun recording.

    Call after ``rerun.init`` and a sink (``rerun.save``, ``rerun.serve_grpc``...). ``history``:
    the latest observed hand poses drawn at each moment (the live view's default).
    """
    import rerun as rr

    bag = Path(bag)
    # Ours first: small, so a viewer streaming the recording shows them before the images arrive.
    urdf = estimate_urdf(bag)
    if urdf is not None:
        # Link names carry the estimate/ prefix, so the meshes hang on the bag's estimate/ frames.
        rr.log_file_from_contents(file_path=Path(f'{ESTIMATE_ENTITY}.urdf'), file_contents=urdf.encode(),
                                  entity_path_prefix=ESTIMATE_ENTITY)
    obs = hand_observations(bag)
    for i, t in enumerate(obs.log_time_ns):
        rr.set_time(LOG_TIMELINE, timestamp=np.datetime64(int(t), 'ns'))
        # The latest `history` detections (every frame the detector saw the hand in, moving ones too).
        recent = slice(max(0, i + 1 - history), i + 1)
        rr.log(OBSERVATION_ENTITY, rr.Ellipsoids3D(centers=obs.centers[recent], half_sizes=obs.half_sizes[recent],
                                                   quaternions=obs.quaternions[recent], colors=(40, 160, 255),
                                                   fill_mode='solid'),
               rr.CoordinateFrame(obs.frame))
    if metrics_csv is not None:
        curve = error_curve(metrics_csv)
        for t, pos, rot in zip(curve['sim_time'], curve['position_mm'], curve['orientation_deg']):
            rr.set_time(LOG_TIMELINE, timestamp=np.datetime64(int(round(t * 1e9)), 'ns'))
            rr.log(f'{ERROR_ENTITY}/position_mm', rr.Scalars(pos))
            rr.log(f'{ERROR_ENTITY}/orientation_deg', rr.Scalars(rot))
    if not summary(bag).complete:
        # Rerun's importer needs the summary a killed recorder never wrote: give it a recovered
        # copy, kept until exit (the importer reads it in the background).
        import atexit
        import shutil
        import tempfile

        tmp = tempfile.mkdtemp(prefix='bag_view_')
        atexit.register(shutil.rmtree, tmp, ignore_errors=True)
        whole = Path(tmp) / bag.name
        print(f'bag_view: {recover(bag, whole).loss}', file=sys.stderr)
        bag = whole
    rr.log_file_from_path(bag)
    rr.send_blueprint(blueprint())


def find_browser() -> str | None:
    """The path of a Chromium-family browser on PATH (Debian's ``chromium`` first), or None."""
    import shutil

    return next((p for p in map(shutil.which, ('chromium', 'chromium-browser', 'google-chrome')) if p), None)


def _screenshot(url: str, out: Path, wait_s: float, size: tuple[int, int]) -> None:
    """Load ``url`` in headless Chromium (software WebGL), wait ``wait_s`` and save a PNG.

    Chromium's own ``--screenshot`` fires before the viewer's WebAssembly has loaded, so this
    drives it over the DevTools protocol and waits in real time.
    """
    import asyncio
    import base64
    import json
    import subprocess
    import tempfile
    import urllib.request

    import websockets

    browser = find_browser()
    if browser is None:
        raise FileNotFoundError('no chromium on PATH (apt-get install chromium)')
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]

    async def shoot() -> bytes:
        with tempfile.TemporaryDirectory() as profile:
            proc = subprocess.Popen([browser, '--headless', '--no-sandbox', '--use-angle=swiftshader',
                                     '--enable-unsafe-swiftshader', f'--window-size={size[0]},{size[1]}',
                                     f'--remote-debugging-port={port}', f'--user-data-dir={profile}', 'about:blank'],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                deadline = time.monotonic() + 30.0
                while True:
                    try:
                        with urllib.request.urlopen(f'http://127.0.0.1:{port}/json') as r:
                            tabs = json.load(r)
                        break
                    except OSError:
                        if time.monotonic() > deadline:
                            raise TimeoutError(f'chromium did not open its DevTools port {port} in 30 s')
                        await asyncio.sleep(0.2)
                target = next(t['webSocketDebuggerUrl'] for t in tabs if t['type'] == 'page')
                # No keepalive pings: a browser busy rendering in software answers them late.
                async with websockets.connect(target, max_size=2 ** 28, ping_interval=None) as ws:
                    ids = iter(range(1, 1 << 30))

                    async def call(method: str, **params: object) -> dict:
                        i = next(ids)
                        await ws.send(json.dumps({'id': i, 'method': method, 'params': params}))
                        while True:
                            reply = json.loads(await ws.recv())
                            if reply.get('id') == i:
                                return reply

                    await call('Page.enable')
                    await call('Page.navigate', url=url)
                    await asyncio.sleep(wait_s)
                    reply = await call('Page.captureScreenshot', format='png')
                    return base64.b64decode(reply['result']['data'])
            finally:
                proc.terminate()
                proc.wait(timeout=10)

    out.write_bytes(asyncio.run(shoot()))


def _check_free(*ports: int) -> None:
    """Raise OSError naming the first of ``ports`` another process listens on (127.0.0.1)."""
    for port in ports:
        with socket.socket() as s:
            if s.connect_ex(('127.0.0.1', port)) == 0:
                raise OSError(f'port {port} is in use (another viewer?); choose others with --port')


def main(argv: list[str] | None = None) -> int:
    """Command line: serve the bag to a browser, save it as .rrd, or screenshot the view."""
    ap = argparse.ArgumentParser(prog='bag_view', description=__doc__.split('\n\n')[0])
    ap.add_argument('bag', type=Path, help='calibration.mcap')
    ap.add_argument('--metrics', type=Path, help="evaluate's metrics.csv (default: beside the bag, if there)")
    ap.add_argument('--save', type=Path, help='write a Rerun recording (.rrd) instead of serving')
    ap.add_argument('--screenshot', type=Path, help='serve, screenshot in headless Chromium, exit')
    ap.add_argument('--wait', type=float, default=150.0, help='screenshot: seconds to let the viewer load [s]')
    ap.add_argument('--port', type=int, default=9090, help='web viewer port (gRPC: port + 1)')
    args = ap.parse_args(argv)
    try:
        summary(args.bag)
    except (FileNotFoundError, BagError) as e:
        print(f'bag_view: {e}', file=sys.stderr)
        return 2
    if args.metrics is not None and not args.metrics.is_file():
        print(f'bag_view: no such metrics file: {args.metrics}', file=sys.stderr)
        return 2
    metrics = args.metrics or (args.bag.parent / 'metrics.csv')
    metrics = metrics if metrics.is_file() else None

    import rerun as rr

    rr.init('body_schema_calibration', recording_id=args.bag.stem)
    if args.save is not None:
        rr.save(args.save)
        log_bag(args.bag, metrics)
        rr.disconnect()
        print(f'wrote {args.save}: open it with `rerun {args.save}`')
        return 0
    url = f'http://127.0.0.1:{args.port}/?url=rerun%2Bhttp://127.0.0.1:{args.port + 1}/proxy'
    if args.screenshot is not None:
        if find_browser() is None:
            print('bag_view: --screenshot needs chromium on PATH (apt-get install chromium)', file=sys.stderr)
            return 2
        _check_free(args.port, args.port + 1)
        # Served from a saved recording by Rerun's own server (a second process): the viewer then
        # loads it at its own pace while this process only drives the browser.
        import subprocess
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            rrd = Path(tmp) / 'view.rrd'
            rr.save(rrd)
            log_bag(args.bag, metrics)
            rr.disconnect()
            # Its own session: `python -m rerun` runs the viewer binary as a child, which must
            # go with it (a left-over server would keep the ports and serve the next screenshot).
            server = subprocess.Popen([sys.executable, '-m', 'rerun', '--serve-web', '--web-viewer-port',
                                       str(args.port), '--port', str(args.port + 1), str(rrd)],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
            try:
                _screenshot(url, args.screenshot, args.wait, (1400, 900))
            finally:
                os.killpg(server.pid, signal.SIGTERM)
                server.wait(timeout=30)
        print(f'wrote {args.screenshot}')
        return 0
    grpc = rr.serve_grpc(grpc_port=args.port + 1)
    log_bag(args.bag, metrics)
    rr.serve_web_viewer(web_port=args.port, open_browser=False, connect_to=grpc)
    print(f'the calibration in the Rerun viewer: {url}  (Ctrl-C to stop)', flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        return 0


if __name__ == '__main__':
    sys.exit(main())
