"""``make bench`` section: every camera encoding and the compressed transport against rgb8.

The simulator's PyBullet world (:class:`icub_sim_bridge.world.SimWorld`, nominal DH table, so
the truth is the description's forward kinematics) renders the left eye for uniformly drawn
configurations of the calibration box, as a calibration run does (the description's camera,
no pixel noise). Each rgb8 frame is re-encoded as a camera of every encoding would deliver it
(:func:`calibration_interfaces.image_conversion.encode_rgb`: Bayer by mosaicking, YUV 4:2:2 with
OpenCV's BT.601 conversion, 16 bits as ``v * 257``) and as image_transport's compressed topic
(JPEG quality 90, PNG), turned into the detector's grey image by the detector's own conversion
(:func:`~calibration_interfaces.image_conversion.message_to_gray` on the message fields), and
detected. Against the rgb8 frame's detections it reports the marker corners' displacement [px],
the hand pose's displacement, and the hand-pose error against the truth; then the detector's
time per frame at 1280x1024 (conversion alone, and conversion + detection + pose).

``main(argv) -> str`` returns a Markdown section (see :mod:`tools.bench`).
Usage: ``python -m tools.encoding_bench [--n 200] [--seed 0] [--timing-frames 20] [--quick]``.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from body_schema import load_robot
from body_schema.kinematics import rotation_angle_deg
from body_schema.noise import PoseDependentNoise
from body_schema.sampling import uniform_configs
from calibration_interfaces.image_conversion import compress, encode_rgb, message_to_gray, rgb_to_image_fields
from marker_detector.detection import HandPoseEstimator
from marker_detector.detector_node import DetectorNodeSettings

__all__ = ['VARIANTS', 'CORNER_TARGET_PX', 'Variant', 'VariantScores', 'message_for', 'measure', 'time_variants',
           'run', 'main']

#: The issue's bound on corner displacement from rgb8 for the lossless encodings [px].
CORNER_TARGET_PX = 0.1
#: The detector node's demosaicing of Bayer images.
DEMOSAICING = DetectorNodeSettings.demosaicing
JPEG_QUALITY = 90
TIMING_SIZE = (1280, 1024)


@dataclass(frozen=True)
class Variant:
    """One way a camera can deliver a frame: a raw encoding, or a compressed codec of rgb8."""

    name: str
    encoding: str
    codec: str = ''          # '' raw; 'jpeg' or 'png': image_transport's compressed topic
    demosaicing: str = DEMOSAICING

    @property
    def lossless(self) -> bool:
        """The grey image is the rgb8 one's exactly (what the encoding keeps of it)."""
        return not self.codec.startswith('jpeg') and not self.encoding.startswith(('bayer', 'uyvy', 'yuyv'))


#: Every camera encoding (the YUV aliases yuv422 / yuv422_yuy2 are uyvy / yuyv), then the codecs.
VARIANTS: tuple[Variant, ...] = (
    *(Variant(e, e) for e in ('rgb8', 'bgr8', 'rgba8', 'bgra8', 'mono8', 'rgb16', 'bgr16', 'rgba16', 'bgra16',
                              'mono16')),
    *(Variant(f'bayer_{p}{b}', f'bayer_{p}{b}') for b in (8, 16) for p in ('rggb', 'bggr', 'gbrg', 'grbg')),
    *(Variant(f'bayer_rggb8, {m}', 'bayer_rggb8', demosaicing=m) for m in ('edge_aware', 'bilinear', 'mosaic')
      if m != DEMOSAICING),
    Variant('uyvy (yuv422)', 'uyvy'), Variant('yuyv (yuv422_yuy2)', 'yuyv'),
    Variant(f'compressed JPEG q{JPEG_QUALITY} (rgb8)', 'rgb8', 'jpeg'),
    Variant('compressed PNG (rgb8)', 'rgb8', 'png'),
)


def message_for(rgb: NDArray[np.uint8], variant: Variant) -> Any:
    """The message fields a camera of ``variant`` would send for ``rgb`` (duck-typed message)."""
    if variant.codec:
        return SimpleNamespace(**compress(encode_rgb(rgb, variant.encoding), variant.encoding, variant.codec,
                                          jpeg_quality=JPEG_QUALITY))
    return SimpleNamespace(**rgb_to_image_fields(rgb, variant.encoding))


@dataclass
class VariantScores:
    """Per variant, over the frames: corner displacement from rgb8 [px] (every corner of every
    marker both found), hand-pose displacement from rgb8, and the errors against the truth of
    this variant's and rgb8's hand poses (all three on the frames where both have a hand)."""

    corners_px: list[float]
    same_markers: int
    hand_diff_mm: list[float]
    hand_diff_deg: list[float]
    pos_err_mm: list[float]
    rot_err_deg: list[float]
    ref_pos_err_mm: list[float]
    ref_rot_err_deg: list[float]
    detected: int


def measure(frames: Sequence[tuple[NDArray[np.uint8], NDArray[np.float64], NDArray[np.float64]]],
            estimator: HandPoseEstimator, k: NDArray[np.float64],
            variants: Sequence[Variant] = VARIANTS) -> dict[str, VariantScores]:
    """Detections of every variant against rgb8's on the same frames.

    Parameters
    ----------
    frames : sequence of (rgb (H, W, 3) uint8, root_T_cam (4, 4), true hand pose (4, 4))
    estimator : HandPoseEstimator
    k : ndarray, shape (3, 3)
    variants : sequence of Variant (the first is the reference, rgb8)
    """
    out = {v.name: VariantScores([], 0, [], [], [], [], [], [], 0) for v in variants}

    def errors(pose: NDArray[np.float64], truth: NDArray[np.float64]) -> tuple[float, float]:
        return (1e3 * float(np.linalg.norm(pose[:3, 3] - truth[:3, 3])),
                float(rotation_angle_deg(pose[:3, :3], truth[:3, :3])))

    for rgb, root_T_cam, truth in frames:
        ref = None
        for v in variants:
            gray = message_to_gray(message_for(rgb, v), v.demosaicing)
            res = estimator.process(gray, k, None, root_T_cam)
            poses = {p.marker_id: p for p in res.markers + res.rejected}      # every marker solved
            hand = res.hand
            if ref is None:
                ref = (poses, hand)
            s = out[v.name]
            s.same_markers += set(poses) == set(ref[0])
            for mid in set(poses) & set(ref[0]):
                s.corners_px += np.linalg.norm(poses[mid].corners - ref[0][mid].corners, axis=1).tolist()
            if hand is None:
                continue
            s.detected += 1
            if ref[1] is not None:
                s.hand_diff_mm.append(1e3 * float(np.linalg.norm(hand.pose[:3, 3] - ref[1].pose[:3, 3])))
                s.hand_diff_deg.append(float(rotation_angle_deg(hand.pose[:3, :3], ref[1].pose[:3, :3])))
                for (pos, rot), (plist, rlist) in ((errors(hand.pose, truth), (s.pos_err_mm, s.rot_err_deg)),
                                                   (errors(ref[1].pose, truth),
                                                    (s.ref_pos_err_mm, s.ref_rot_err_deg))):
                    plist.append(pos)
                    rlist.append(rot)
    return out


def _best_of(fn: Callable[[], Any], repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def time_variants(frames: Sequence[tuple[NDArray[np.uint8], NDArray[np.float64]]], estimator: HandPoseEstimator,
                  k: NDArray[np.float64], variants: Sequence[Variant] = VARIANTS,
                  repeats: int = 3) -> dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """Seconds per frame of the detector's conversion, and of conversion + detection + pose.

    Fastest of ``repeats`` runs per frame, so that another process pre-empting this one does
    not count. Returns ``{variant: (convert seconds, total seconds)}``, one value per frame.
    """
    out = {}
    for v in variants:
        msgs = [(message_for(rgb, v), root_T_cam) for rgb, root_T_cam in frames]
        conv = [_best_of(lambda m=m: message_to_gray(m, v.demosaicing), repeats) for m, _ in msgs]
        total = [_best_of(lambda m=m, t=t: estimator.process(message_to_gray(m, v.demosaicing), k, None, t), repeats)
                 for m, t in msgs]
        out[v.name] = (np.array(conv), np.array(total))
    return out


def _render(world: Any, model: Any, configs: NDArray[np.float64], size: tuple[int, int]) -> tuple[Any, list]:
    intr = model.camera.scaled(*size)
    root_T_cam = model.camera_pose('left')
    frames = []
    for q in configs:
        world.set_joint_positions(q)
        frames.append((world.render(root_T_cam, intr), root_T_cam, model.forward_kinematics(q)))
    return intr, frames


def _fmt(values: Sequence[float], fn: Callable[[NDArray[np.float64]], float], nd: int = 3) -> str:
    return f'{fn(np.asarray(values)):.{nd}f}' if len(values) else 'n/a'


def _p95(a: NDArray[np.float64]) -> float:
    return float(np.percentile(a, 95))


def run(n: int = 200, seed: int = 0, timing_frames: int = 20, robot_name: str = 'icub_right_arm',
        repeats: int = 5) -> str:
    """Run the study and return the Markdown section."""
    from icub_sim_bridge.world import SimWorld

    t_start = time.perf_counter()
    model = load_robot(robot_name)
    est = HandPoseEstimator(model, PoseDependentNoise.for_robot(model))
    configs = uniform_configs(model.calibration_box, n, seed)
    with SimWorld(model) as world:
        intr, frames = _render(world, model, configs, (model.camera.width, model.camera.height))
        # Timing at 1280x1024 on configurations where the rgb8 frame shows the hand.
        big_intr, big = _render(world, model, configs[:max(4 * timing_frames, timing_frames)], TIMING_SIZE)
    big = [(rgb, t) for rgb, t, _ in big
           if est.process(message_to_gray(message_for(rgb, VARIANTS[0])), big_intr.K, None, t).hand is not None]
    big = big[:timing_frames]
    scores = measure(frames, est, intr.K)
    times = time_variants(big, est, big_intr.K, repeats=repeats) if big else {}

    ref = scores[VARIANTS[0].name]
    lines = ['## Camera encodings and the compressed transport', '',
             f'{n} uniform configurations of the calibration box (seed {seed}), left eye at '
             f'{intr.width}x{intr.height} (the run\'s camera, no pixel noise), rendered by the simulator; each rgb8 '
             f'frame re-encoded as a camera of that encoding delivers it (Bayer: the mosaic; YUV 4:2:2: OpenCV\'s '
             f'BT.601; 16-bit: v * 257) or as image_transport\'s compressed topic, converted by the detector\'s '
             f'conversion (Bayer demosaicing: the node\'s default, {DEMOSAICING}, unless the row names another) '
             f'and detected. rgb8 found a hand in {ref.detected} frames. Corner displacement: every '
             f'corner of every marker found in both this and the rgb8 frame (target for the lossless encodings '
             f'<= {CORNER_TARGET_PX:g} px); hand displacement: the hand pose against the rgb8 frame\'s, where both '
             f'have one; error: against the true hand pose, on those same frames, this encoding\'s and '
             f'rgb8\'s.', '',
             '| encoding | same markers as rgb8 | corner displacement median / p95 / max [px] | hand displacement '
             'median / max [mm] | hand displacement median / max [deg] | hands (rgb8: '
             f'{ref.detected}) | error median pos [mm], this / rgb8 | error median rot [deg], this / rgb8 |',
             '|---|---|---|---|---|---|---|---|']
    for v in VARIANTS:
        s = scores[v.name]
        corners = f'{_fmt(s.corners_px, np.median)} / {_fmt(s.corners_px, _p95)} / {_fmt(s.corners_px, np.max)}'
        if v.lossless:
            ok = len(s.corners_px) and max(s.corners_px) <= CORNER_TARGET_PX
            corners += '' if ok else ' (MISSES the target)'
        lines.append(f'| {v.name} | {s.same_markers}/{n} | {corners} | {_fmt(s.hand_diff_mm, np.median, 3)} / '
                     f'{_fmt(s.hand_diff_mm, np.max, 3)} | {_fmt(s.hand_diff_deg, np.median, 3)} / '
                     f'{_fmt(s.hand_diff_deg, np.max, 3)} | {s.detected} | {_fmt(s.pos_err_mm, np.median, 3)} / '
                     f'{_fmt(s.ref_pos_err_mm, np.median, 3)} | {_fmt(s.rot_err_deg, np.median, 3)} / '
                     f'{_fmt(s.ref_rot_err_deg, np.median, 3)} |')
    if times:
        lines += ['', f'Detector time per frame at {TIMING_SIZE[0]}x{TIMING_SIZE[1]} ({len(big)} frames showing the '
                  f'hand, fastest of {repeats} runs each, one core): the conversion from the message to grey, and '
                  f'conversion + detection + pose (what the node does per frame).', '',
                  '| encoding | conversion median / p95 [ms] | conversion + detection + pose median / p95 [ms] |',
                  '|---|---|---|']
        for v in VARIANTS:
            conv, total = times[v.name]
            lines.append(f'| {v.name} | {1e3 * np.median(conv):.2f} / {1e3 * _p95(conv):.2f} | '
                         f'{1e3 * np.median(total):.2f} / {1e3 * _p95(total):.2f} |')
    lines += ['', f'_{len(frames)} + {len(big)} frames, {time.perf_counter() - t_start:.0f} s._', '']
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--n', type=int, default=200, help='configurations of the calibration box')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--timing-frames', type=int, default=20, help='1280x1024 frames timed per encoding')
    ap.add_argument('--robot', default='icub_right_arm')
    ap.add_argument('--quick', action='store_true', help='40 configurations, 5 timed frames')
    args = ap.parse_args(list(argv) if argv is not None else None)
    if args.quick:
        return run(40, args.seed, 5, args.robot)
    return run(args.n, args.seed, args.timing_frames, args.robot)


if __name__ == '__main__':
    print(main(sys.argv[1:]))
