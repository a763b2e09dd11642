r"""`flyslam import FORMAT PATH --out FILE.mcap`: convert a public stereo dataset or a ROS bag into a recording.

examples:
  flyslam import kitti  /data/kitti/odometry --sequence 05 --out kitti05.mcap
  flyslam import euroc  /data/euroc/MH_01_easy --out mh01.mcap
  flyslam import euroc  /data/tumvi/dataset-room1_512_16 --camchain dso/camchain.yaml --out room1.mcap
  flyslam import middlebury /data/middlebury/Motorcycle-perfect --scale 0.25 --out moto.mcap

  # ROS 2 bag folder (or ROS 1 .bag), calibration from the sibling camera_info topics:
  flyslam import rosbag ./zed_run --left /zed/left/image_raw --right /zed/right/image_raw --out zed.mcap
  # EuRoC / TUM-VI bag with its Kalibr camchain (fisheye lenses rectified once; topics from rostopic):
  flyslam import rosbag dataset-room1_512_16.bag --camchain camchain-imucam.yaml \
      --truth /vrpn_client/raw_transform --truth-frame imu --out room1.mcap
  # camera_info on other topics, ground truth from an Odometry topic, looser stereo sync:
  flyslam import rosbag run.bag --left /cam/left/image_rect --right /cam/right/image_rect \
      --left-info /cam/left/info --right-info /cam/right/info --truth /odom --sync-tolerance-ms 10 --out run.mcap

rosbag: images are sensor_msgs/Image (mono8, mono16, rgb8, bgr8, rgba8, bgra8, bayer_*8) or CompressedImage. Each
left image is paired with the right image nearest in header stamp, within --sync-tolerance-ms (default
5 ms); unpaired images are skipped and counted. Calibration comes from --camchain (Kalibr, pinhole with
equidistant or radtan lenses) or else from the first CameraInfo of each camera (default topic: the
image topic's sibling camera_info; K, D raw and R, P rectification as in ROS image_proc; *image_rect*
topics or --rectified: P only). --truth takes PoseStamped, PoseWithCovarianceStamped, TransformStamped
or Odometry; --truth-frame says whose pose it is (body: a REP-103 body frame at the cameras; optical:
the left camera; imu: the camchain's IMU via T_cam_imu).

The recording replays like a live source (`flyslam replay`): rectified frames on stereo/frame (PNG by
default: lossless), the calibration on stereo/calibration and as metadata, ground truth on truth/pose
(and truth/depth for Middlebury). Frames and conventions: common/importers/base.py.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from common.importers import FORMATS, DatasetLayoutError, write_recording


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="flyslam import", description=__doc__.split("\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n", 2)[2])
    rosbag_defaults = _rosbag_defaults()
    p.add_argument("format", choices=FORMATS)
    p.add_argument("path", help="dataset folder (KITTI: root with --sequence, or the sequence folder; "
                                "EuRoC: the folder holding mav0; Middlebury: the scene folder; rosbag: a ROS 1 .bag "
                                "file or a ROS 2 bag folder)")
    p.add_argument("--out", "-o", required=True, help="MCAP file to write")
    p.add_argument("--sequence", help="KITTI sequence number (with a dataset root)")
    p.add_argument("--max-frames", type=int, default=None, help="import only the first N frames")
    p.add_argument("--encoding", choices=("png", "jpeg"), default="png", help="frame compression (default: png)")
    p.add_argument("--quality", type=int, default=95, help="JPEG quality")
    p.add_argument("--robot", default="rig", help="key prefix of the recording (default: rig)")
    p.add_argument("--scale", type=float, default=1.0, help="Middlebury: resize factor in (0, 1]")
    p.add_argument("--repeat", type=int, default=1, help="Middlebury: write the pair N times, 10 Hz")
    bag = p.add_argument_group("rosbag (and --camchain for euroc)")
    bag.add_argument("--left", metavar="TOPIC", help="left image topic (default with --camchain: its cam0 rostopic)")
    bag.add_argument("--right", metavar="TOPIC", help="right image topic (default with --camchain: its cam1 rostopic)")
    bag.add_argument("--left-info", metavar="TOPIC", help="left CameraInfo topic (default: <left namespace>/camera_info)")
    bag.add_argument("--right-info", metavar="TOPIC", help="right CameraInfo topic (default: <right namespace>/camera_info)")
    bag.add_argument("--camchain", metavar="FILE", help="Kalibr camchain.yaml (rosbag: instead of the camera_info "
                                                         "topics; euroc: instead of the sensor.yaml files)")
    bag.add_argument("--rectified", action="store_true", help="the images are already rectified: use CameraInfo P only")
    bag.add_argument("--truth", metavar="TOPIC", help="ground-truth pose topic (PoseStamped, PoseWithCovarianceStamped, "
                                                      "TransformStamped or Odometry)")
    bag.add_argument("--truth-frame", choices=rosbag_defaults["truth_frames"], default="body",
                     help="whose pose --truth gives: body (REP-103, at the cameras; default), optical (left "
                          "camera), imu (camchain T_cam_imu)")
    bag.add_argument("--sync-tolerance-ms", type=float, default=rosbag_defaults["sync_ms"],
                     help="largest left-right header-stamp difference of a pair (default: %(default)g ms)")
    return p


def _rosbag_defaults() -> dict:
    from common.importers.rosbag import DEFAULT_SYNC_TOLERANCE_MS, TRUTH_FRAMES
    return {"sync_ms": DEFAULT_SYNC_TOLERANCE_MS, "truth_frames": TRUTH_FRAMES}


def load(args):
    if args.format == "kitti":
        from common.importers.kitti import load_kitti
        return load_kitti(args.path, sequence=args.sequence, max_frames=args.max_frames)
    if args.format == "euroc":
        from common.importers.euroc import load_euroc
        return load_euroc(args.path, max_frames=args.max_frames, camchain=args.camchain)
    if args.format == "rosbag":
        from common.importers.rosbag import load_rosbag
        return load_rosbag(args.path, left=args.left, right=args.right, left_info=args.left_info,
                           right_info=args.right_info, camchain=args.camchain, truth=args.truth,
                           truth_frame=args.truth_frame, sync_tolerance_ms=args.sync_tolerance_ms,
                           rectified=args.rectified, max_frames=args.max_frames)
    from common.importers.middlebury import load_middlebury
    return load_middlebury(args.path, scale=args.scale, repeat=args.repeat)


class _Progress:
    """'frames done/total' on stderr, at most twice a second and at the end."""

    def __init__(self):
        self.last = 0.0

    def __call__(self, done: int, total: int) -> None:
        now = time.monotonic()
        if done == total or now - self.last >= 0.5:
            self.last = now
            print(f"frames {done}/{total}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.max_frames is not None and args.max_frames < 1:
        print("flyslam import: --max-frames must be at least 1", file=sys.stderr)
        return 2
    try:
        dataset = load(args)
    except (DatasetLayoutError, ValueError) as e:  # CalibrationError is a ValueError too
        print(f"flyslam import: {e}", file=sys.stderr)
        return 2
    print(f"importing {dataset.name} → {args.out}", file=sys.stderr, flush=True)
    out = Path(args.out)
    try:
        summary = write_recording(dataset, out, robot=args.robot, encoding=args.encoding,
                                  quality=args.quality, progress=_Progress())
    except (DatasetLayoutError, ValueError) as e:  # e.g. an unreadable image half-way
        out.unlink(missing_ok=True)  # no half-written recording that looks complete
        print(f"flyslam import: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:        # the same: a cut import would pass for the whole sequence
        out.unlink(missing_ok=True)
        print(f"flyslam import: interrupted; {out} not written", file=sys.stderr)
        return 130
    print(summary.format())
    return 0


if __name__ == "__main__":
    sys.exit(main())
