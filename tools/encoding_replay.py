"""A recorded rgb8 run re-detected as a Bayer or JPEG camera would have seen it, then re-calibrated.

Two launcher runs with different encodings leave the same seed's trajectory at the first
attempt whose outcome differs (a marker detected in one image and not in the other), after
which their errors differ by what the selector chose, not by the images. This isolates the
images: for every camera frame recorded in an rgb8 run's bag (``scripts/run_calibration.sh``
records the images), the frame is re-encoded (:mod:`tools.encoding_bench`'s variants), the
detector's conversion and pose estimation run on it with the detector's defaults, and its
``/hand_pose`` replaces the recorded one in a copy of the bag; the estimator is then re-run on
each copy with the run's parameters (:func:`dh_estimator.evaluate.evaluate_bag`), against the
copy re-detected from the rgb8 frames themselves (which must reproduce the recorded hand poses:
checked, so the detector settings are the run's; its re-run must give the bag's own).

Usage (from the repository root)::

    python -m tools.encoding_replay results/rgb8/seed_*/calibration.mcap --output results/encoding-replay
    python -m tools.encoding_replay --failures results/compressed/seed_1 --variant 'compressed JPEG q90 (rgb8)'

The second form asks of a run on another encoding whether its failed attempts were the
encoding's doing: each iteration's reached configuration is rendered on the run's real robot
(``/body_schema/true``) and detected as rgb8 and as the run's encoding.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from body_schema import load_robot
from calibration_interfaces import mcap_reader
from calibration_interfaces.image_conversion import image_to_array, message_to_gray
from calibration_interfaces.messages import matrix_to_pose_msg, pose_msg_to_matrix
from calibration_interfaces.noise import NoiseSettings
from calibration_interfaces.parameters import read_params_file
from marker_detector.detection import DetectorConfig, HandPoseEstimator
from tools.encoding_bench import VARIANTS, Variant, message_for

__all__ = ['REPLAYED', 'redetect', 'failures', 'main']

#: rgb8 (the reference, re-detected), the detector's Bayer path, cv_bridge's, the photosites as
#: grey, and JPEG q90.
REPLAYED: tuple[Variant, ...] = tuple(v for v in VARIANTS if v.name in (
    'rgb8', 'bayer_rggb8', 'bayer_rggb8, bilinear', 'bayer_rggb8, mosaic', f'compressed JPEG q{90} (rgb8)'))
IMAGE = '/camera/left/image_raw'
ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / 'ros2_ws' / 'src' / 'calibration_bringup' / 'config'


def redetect(src: Path, dst: Path, variant: Variant, robot: str = 'icub_right_arm') -> tuple[int, float]:
    """Copy ``src`` to ``dst`` with ``/hand_pose`` re-detected from the left images as ``variant``.

    Returns
    -------
    (int, float)
        Hand poses written, and the largest difference [m or rad, per pose component] from the
        recorded hand pose of the same stamp (over the stamps both have; for the rgb8 variant it
        must be 0: the detector settings are the run's).
    """
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import CameraInfo, Image

    from calibration_bringup.mcap_writer import McapBagWriter

    model = load_robot(robot)
    estimator = HandPoseEstimator(model, NoiseSettings().build(model), DetectorConfig())
    info = pose = None
    for m in mcap_reader.read_raw(src, ['/camera/left/camera_info', '/camera/left/pose']):
        if m.topic.endswith('camera_info') and info is None:
            info = deserialize_message(m.data, CameraInfo)
        elif m.topic.endswith('pose') and pose is None:
            from geometry_msgs.msg import PoseStamped
            pose = pose_msg_to_matrix(deserialize_message(m.data, PoseStamped).pose)
    if info is None or pose is None:
        raise ValueError(f'{src}: no camera_info or camera pose for the left eye')
    k, d = np.reshape(info.k, (3, 3)), np.asarray(info.d, float)
    # The recorded hand poses by image stamp: their pose, and their log and publish times, which
    # a re-detected one takes over (the re-run orders by log time; an rgb8 copy is then the bag).
    recorded = {}
    for m in mcap_reader.read_raw(src, ['/hand_pose']):
        h = deserialize_message(m.data, PoseWithCovarianceStamped)
        recorded[(h.header.stamp.sec, h.header.stamp.nanosec)] = (pose_msg_to_matrix(h.pose.pose), m.log_time_ns,
                                                                   m.publish_time_ns)
    summary = mcap_reader.summary(src)
    written, worst = 0, 0.0
    with McapBagWriter(dst) as out:
        out.add_metadata('recording', mcap_reader.recording_metadata(src))
        for t in summary.topics.values():
            if t.name != IMAGE:                      # the copy needs no images
                out.add_channel(t.name, t.type, t.offered_qos, t.type_hash)
        for m in mcap_reader.read_raw(src):
            if m.topic == '/hand_pose':
                continue
            if m.topic != IMAGE:
                out.write(m.topic, m.data, m.log_time_ns, m.publish_time_ns)
                continue
            img = deserialize_message(m.data, Image)
            gray = message_to_gray(message_for(image_to_array(img, 'rgb8'), variant), variant.demosaicing)
            hand = estimator.process(gray, k, d, pose).hand
            if hand is None:
                continue
            msg = PoseWithCovarianceStamped()
            msg.header.stamp, msg.header.frame_id = img.header.stamp, model.root_frame
            msg.pose.pose = matrix_to_pose_msg(hand.pose)
            msg.pose.covariance = [float(v) for v in hand.covariance.reshape(36)]
            key = (img.header.stamp.sec, img.header.stamp.nanosec)
            times = (m.log_time_ns, m.publish_time_ns)        # a frame rgb8 did not detect: the image's
            if key in recorded:
                times = recorded[key][1:]
                worst = max(worst, float(np.abs(hand.pose - recorded[key][0]).max()))
            out.write('/hand_pose', serialize_message(msg), *times)
            written += 1
    return written, worst


def failures(run: Path, variant: Variant, robot: str = 'icub_right_arm') -> dict[tuple[str, bool, bool], int]:
    """Iterations of a launcher run by (outcome, rgb8 sees the hand, ``variant`` sees it), each
    reached configuration rendered on the run's real robot for the left eye."""
    import json

    from calibration_interfaces.messages import msg_to_table
    from icub_sim_bridge.world import SimWorld

    model = load_robot(robot)
    true = next(msg_to_table(m, model.n_joints)
                for _, _, m in mcap_reader.read_messages(run / 'calibration.mcap', ['/body_schema/true']))
    estimator = HandPoseEstimator(model, NoiseSettings().build(model), DetectorConfig())
    root_T_cam, intr = model.camera_pose('left'), model.camera
    out: dict[tuple[str, bool, bool], int] = {}
    with SimWorld(model, true) as world:
        for line in (run / 'progress.jsonl').read_text().splitlines():
            record = json.loads(line)
            world.set_joint_positions(np.radians(record['reached_deg']))
            rgb = world.render(root_T_cam, intr)
            seen = [estimator.process(message_to_gray(message_for(rgb, v), v.demosaicing), intr.K, None,
                                      root_T_cam).hand is not None for v in (VARIANTS[0], variant)]
            key = (record['outcome'], *seen)
            out[key] = out.get(key, 0) + 1
    return out


def main(argv: Sequence[str] | None = None) -> int:
    from dh_estimator.evaluate import EvaluationSettings, evaluate_bag

    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('bags', nargs='*', type=Path, help="rgb8 runs' calibration.mcap (with images)")
    ap.add_argument('--output', type=Path, help='where the re-detected copies go')
    ap.add_argument('--robot', default='icub_right_arm')
    ap.add_argument('--failures', nargs='+', type=Path, default=[], help='run directories to check instead')
    ap.add_argument('--variant', default=REPLAYED[-1].name, help='their encoding (a tools.encoding_bench variant)')
    args = ap.parse_args(list(argv) if argv is not None else None)
    if args.failures:
        variant = next(v for v in VARIANTS if v.name == args.variant)
        for run in args.failures:
            for (outcome, rgb8, other), n in sorted(failures(run, variant, args.robot).items()):
                print(f'{run}: {n} {outcome}: rgb8 {"sees" if rgb8 else "does not see"} the hand, {variant.name} '
                      f'{"sees" if other else "does not see"} it')
        return 0
    if not args.bags or args.output is None:
        ap.error('give rgb8 bags and --output, or --failures RUN_DIR ...')
    settings = EvaluationSettings.from_parameters(read_params_file(CONFIG / 'estimator.yaml', 'dh_estimator'))
    finals: dict[str, list[tuple[float, float]]] = {v.name: [] for v in REPLAYED}
    print('| bag | encoding | hand poses | final position [mm] | final orientation [deg] |\n|---|---|---|---|---|')
    for bag in args.bags:
        for i, v in enumerate(REPLAYED):
            dst = args.output / f'{bag.parent.name}-{i}.mcap'
            dst.parent.mkdir(parents=True, exist_ok=True)
            written, worst = redetect(bag, dst, v, args.robot)
            if v.name == 'rgb8' and worst > 1e-9:
                raise RuntimeError(f'{bag}: rgb8 re-detection differs from the recorded hand poses by {worst:g}: '
                                   f'the detector settings are not the run\'s')
            last = evaluate_bag(dst, settings).rows[-1]
            if v.name == 'rgb8':
                original = evaluate_bag(bag, settings).rows[-1]
                if abs(original.position_mm - last.position_mm) > 1e-9:
                    raise RuntimeError(f'{bag}: the rgb8 copy re-runs to {last.position_mm} mm, the bag to '
                                       f'{original.position_mm} mm')
            finals[v.name].append((last.position_mm, last.orientation_deg))
            print(f'| {bag.parent.name} | {v.name} | {written} | {last.position_mm:.3f} | {last.orientation_deg:.4f} |',
                  flush=True)
    ref = np.array(finals['rgb8'])
    print(f'\nOver {len(args.bags)} runs (same frames, same trajectory):\n')
    for name, values in finals.items():
        a = np.array(values)
        print(f'- {name}: position mean {a[:, 0].mean():.3f} mm (median {np.median(a[:, 0]):.3f}, '
              f'{a[:, 0].min():.3f}-{a[:, 0].max():.3f}), orientation mean {a[:, 1].mean():.4f} deg; '
              f'ratio of means to rgb8: {a[:, 0].mean() / ref[:, 0].mean():.3f} (position), '
              f'{a[:, 1].mean() / ref[:, 1].mean():.3f} (orientation); per run (position): '
              f'{np.round(a[:, 0] / ref[:, 0], 3).tolist()}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
