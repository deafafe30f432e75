"""``companion calibrate``: camera intrinsics and distortion from checkerboard or ChArUco views.

Frames come from a folder of images, a video file or a live camera (any perception/sources.py spec).
The board is found in each frame (``cv2.findChessboardCornersSB``, or ``cv2.aruco.CharucoDetector``),
views too close to the previous kept one are skipped (a board held still gives one view, not fifty),
then ``cv2.calibrateCamera`` (OpenCV's 5-coefficient model k1, k2, p1, p2, k3). The result is written as
a camera YAML that ``--config`` accepts (the ``camera:`` section), the RMS reprojection error in its
header comment.

A poor set is refused with the reason, one line, exit 2: too few views, too little of the image
covered by board corners (the distortion far from the centre would be a guess), or a high error; and a set
that fits well but cannot tell the focal length: boards never tilted (fronto-parallel views fit any focal
length once the distortion bends to match: 30 of them gave fx 3646 for a true 500 at RMS 0.015 px), or a
result no lens gives (a field of view below --min-fov, a principal point far off centre, a distortion that
folds the image, a parameter the views leave uncertain).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
COVERAGE_GRID = 8  # the image is cut into GRID x GRID cells; coverage = share of cells with a corner
MAX_REL_STD = 0.02  # largest accepted standard deviation of fx, fy, cx, cy, as a share of the value
MAX_CENTRE_OFFSET = 0.25  # principal point: at most this share of the width/height from the image centre


class CalibrationRefused(ValueError):
    """A set of views that would give a bad calibration (one line: why)."""


@dataclass(frozen=True)
class Board:
    kind: str  # "checkerboard" or "charuco"
    cols: int  # squares across (checkerboard: inner corners across = cols - 1)
    rows: int
    square: float  # m (only scales the extrinsics; intrinsics do not depend on it)
    marker: float = 0.0  # ChArUco marker side, m
    dictionary: str = "DICT_4X4_50"

    def object_points(self) -> np.ndarray:
        """Inner corners on the board plane (z = 0), row-major, in OpenCV's order for the checkerboard."""
        nx, ny = self.cols - 1, self.rows - 1
        g = np.mgrid[0:nx, 0:ny].T.reshape(-1, 2).astype(np.float32) * self.square
        return np.hstack([g, np.zeros((len(g), 1), np.float32)])


@dataclass
class Views:
    size: tuple[int, int] | None = None  # (width, height)
    object_points: list[np.ndarray] = field(default_factory=list)
    image_points: list[np.ndarray] = field(default_factory=list)
    frames_seen: int = 0


@dataclass
class Result:
    K: np.ndarray
    dist: np.ndarray
    rms: float
    views: int
    coverage: float
    size: tuple[int, int]


class Detector:
    def __init__(self, board: Board) -> None:
        self.board = board
        self._charuco = None
        if board.kind == "charuco":
            d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
            b = cv2.aruco.CharucoBoard((board.cols, board.rows), board.square, board.marker, d)
            self._charuco = (cv2.aruco.CharucoDetector(b), b)

    def find(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(object points Nx3, image points Nx2) of the board in the image, or None."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if self._charuco is None:
            pattern = (self.board.cols - 1, self.board.rows - 1)
            ok, corners = cv2.findChessboardCornersSB(gray, pattern, flags=cv2.CALIB_CB_ACCURACY)
            if not ok:
                return None
            return self.board.object_points(), corners.reshape(-1, 2).astype(np.float32)
        det, b = self._charuco
        corners, ids, _, _ = det.detectBoard(gray)
        if ids is None or len(ids) < 6:  # fewer corners constrain a homography too weakly
            return None
        obj = b.getChessboardCorners()[ids.ravel()].astype(np.float32)
        return obj, corners.reshape(-1, 2).astype(np.float32)


def coverage(image_points: list[np.ndarray], size: tuple[int, int], grid: int = COVERAGE_GRID) -> float:
    """Share of the image's grid x grid cells that hold at least one detected corner."""
    w, h = size
    cells = np.zeros((grid, grid), bool)
    for pts in image_points:
        ix = np.clip((pts[:, 0] / w * grid).astype(int), 0, grid - 1)
        iy = np.clip((pts[:, 1] / h * grid).astype(int), 0, grid - 1)
        cells[iy, ix] = True
    return float(cells.mean())


def frames_from(source: str, max_frames: int, every: int) -> Any:
    """Yield BGR frames from a folder of images, a video file or a live camera spec."""
    p = Path(source)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise CalibrationRefused(f"{source}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
        for f in files[::every][:max_frames]:
            img = cv2.imread(str(f), cv2.IMREAD_COLOR)
            if img is None:
                raise CalibrationRefused(f"{f}: not a readable image")
            yield img
        return
    from perception.sources import SourceError, open_source

    try:
        src = open_source(source, realtime=not p.is_file())  # a file: every frame, no dropping
    except SourceError as e:
        raise CalibrationRefused(str(e)) from None
    try:
        n = k = 0
        while n < max_frames:
            got = src.read(2.0)
            if got is None:
                if src.ended:
                    return
                continue
            k += 1
            if (k - 1) % every:
                continue
            n += 1
            yield got[1]
    finally:
        src.close()


def collect(frames: Any, board: Board, min_shift_px: float = 10.0) -> Views:
    """Board views from the frames; a view whose corners moved < min_shift_px (median) from the last kept
    one is the same view again and is skipped."""
    det = Detector(board)
    views = Views()
    last: tuple[np.ndarray, np.ndarray] | None = None
    for img in frames:
        views.frames_seen += 1
        size = (img.shape[1], img.shape[0])
        if views.size is None:
            views.size = size
        elif size != views.size:
            raise CalibrationRefused(f"frame {views.frames_seen}: size {size[0]}x{size[1]} differs from the first "
                                     f"frame's {views.size[0]}x{views.size[1]}")
        found = det.find(img)
        if found is None:
            continue
        obj, pts = found
        same = last is not None and len(last[1]) == len(pts) and np.array_equal(last[0], obj)
        if same and float(np.median(np.linalg.norm(pts - last[1], axis=1))) < min_shift_px:
            continue
        views.object_points.append(obj)
        views.image_points.append(pts)
        last = (obj, pts)
    return views


def tilt_spread(rvecs: Any) -> float:
    """How much the board was tilted, deg: the RMS of the board normal's offset from the optical axis along
    its least-tilted direction (sqrt of the smaller eigenvalue of the normals' second moment in the image
    plane). Zhang's calibration needs tilts about two axes; boards turned only about one axis, or not at
    all, leave the focal length to trade against the distortion."""
    tilts = []
    for r in rvecs:
        n = cv2.Rodrigues(np.asarray(r, float))[0][:, 2]
        tilts.append(n[:2] if n[2] > 0 else -n[:2])
    t = np.asarray(tilts, float)
    smallest = float(np.linalg.eigvalsh(t.T @ t / len(t))[0])
    return float(np.degrees(np.arcsin(min(1.0, np.sqrt(max(smallest, 0.0))))))


def plausibility_problem(K: np.ndarray, dist: np.ndarray, std: np.ndarray, size: tuple[int, int],
                         min_fov: float) -> str | None:
    """Why a calibrated camera is not a plausible lens (one line), or None."""
    from companion.cameramodel import distortion_problem

    w, h = size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    fov = float(np.degrees(2.0 * np.arctan(w / 2.0 / fx))) if fx > 0 else 0.0
    if not (fx > 0 and fy > 0) or fov < min_fov:
        return (f"implausible focal length fx {fx:.0f} px: a {fov:.1f} deg field of view across {w} px "
                f"(< --min-fov {min_fov:g} deg)")
    if not 0.5 <= fx / fy <= 2.0:
        return f"implausible pixel aspect fx/fy {fx / fy:.2f} (fx {fx:.0f}, fy {fy:.0f} px)"
    if abs(cx - w / 2) > MAX_CENTRE_OFFSET * w or abs(cy - h / 2) > MAX_CENTRE_OFFSET * h:
        return f"implausible principal point ({cx:.0f}, {cy:.0f}) px, far from the image centre ({w / 2:g}, {h / 2:g})"
    for name, value, sd in zip(("fx", "fy", "cx", "cy"), (fx, fy, cx, cy), std[:4], strict=True):
        if not np.isfinite(sd) or sd > MAX_REL_STD * abs(value):
            return f"{name} {value:.1f} px is uncertain (std {sd:.3g} px > {MAX_REL_STD:.0%}): add tilted views"
    problem = distortion_problem(K, dist, w, h)
    return f"distortion {problem}" if problem else None


def calibrate(views: Views, min_views: int = 10, min_coverage: float = 0.5, max_error: float = 1.0,
              min_tilt: float = 8.0, min_fov: float = 15.0) -> Result:
    """Intrinsics + distortion, or CalibrationRefused with the reason."""
    n = len(views.image_points)
    if views.size is None:
        raise CalibrationRefused("no frames")
    if n < min_views:
        raise CalibrationRefused(f"too few views: the board was found in {n} distinct view(s) of "
                                 f"{views.frames_seen} frame(s), need >= {min_views}")
    cov = coverage(views.image_points, views.size)
    if cov < min_coverage:
        raise CalibrationRefused(f"too little of the image covered: board corners in {cov:.0%} of it, need >= "
                                 f"{min_coverage:.0%} (move the board to the edges and corners)")
    rms, K, dist, rvecs, _, std, _, _ = cv2.calibrateCameraExtended(views.object_points, views.image_points,
                                                                    views.size, None, None)
    if not np.isfinite(rms) or rms > max_error:
        raise CalibrationRefused(f"reprojection error {rms:.2f} px > {max_error:.2f} px (blurred frames, a board "
                                 "that is not flat, or wrong --cols/--rows)")
    tilt = tilt_spread(rvecs)
    if tilt < min_tilt:
        raise CalibrationRefused(f"the board was hardly tilted: {tilt:.1f} deg RMS about its least-tilted axis, "
                                 f"need >= {min_tilt:g} deg (tilt it 20-45 deg up, down, left and right; "
                                 "square-on views cannot tell the focal length)")
    problem = plausibility_problem(K, dist.ravel()[:5], std.ravel(), views.size, min_fov)
    if problem:
        raise CalibrationRefused(problem)
    return Result(K, dist.ravel()[:5], float(rms), n, cov, views.size)


def camera_yaml(r: Result, source: str) -> str:
    """The ``camera:`` section a ``--config`` overlay takes, with the quality in the header."""
    K = r.K
    body = {"camera": {"width": int(r.size[0]), "height": int(r.size[1]), "fx": round(float(K[0, 0]), 3),
                       "fy": round(float(K[1, 1]), 3), "cx": round(float(K[0, 2]), 3), "cy": round(float(K[1, 2]), 3),
                       "distortion": [float(f"{d:.8g}") for d in r.dist]}}
    head = (f"# companion calibrate {source}\n# RMS reprojection error {r.rms:.3f} px over {r.views} views, "
            f"board corners in {r.coverage:.0%} of the image\n# OpenCV model: distortion = k1, k2, p1, p2, k3\n")
    return head + yaml.safe_dump(body, sort_keys=False)


# ------------------------------------------------------------------------------------------------ CLI


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("calibrate", help="camera intrinsics + distortion from checkerboard/ChArUco views",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", help="folder of images, video file, or camera (V4L2 index, rtsp://, GStreamer)")
    p.add_argument("--board", choices=("checkerboard", "charuco"), default="checkerboard")
    p.add_argument("--cols", type=int, default=10, help="squares across the board (default 10: 9 inner corners)")
    p.add_argument("--rows", type=int, default=7, help="squares down the board (default 7: 6 inner corners)")
    p.add_argument("--square", type=float, default=0.025, help="square side, m")
    p.add_argument("--marker", type=float, default=0.018, help="ChArUco marker side, m")
    p.add_argument("--dictionary", default="DICT_4X4_50", help="ChArUco ArUco dictionary (cv2.aruco name)")
    p.add_argument("--every", type=int, default=1, help="use every n-th frame")
    p.add_argument("--max-frames", type=int, default=2000, help="frames to look at, at most")
    p.add_argument("--min-views", type=int, default=10)
    p.add_argument("--min-coverage", type=float, default=0.5, help="share of the image the corners must reach")
    p.add_argument("--max-error", type=float, default=1.0, help="largest accepted RMS reprojection error, px")
    p.add_argument("--min-tilt", type=float, default=8.0,
                   help="least RMS board tilt about its least-tilted axis, deg (square-on views are degenerate)")
    p.add_argument("--min-fov", type=float, default=15.0, help="narrowest plausible horizontal field of view, deg")
    p.add_argument("-o", "--output", default="camera_calibrated.yaml", help="camera YAML to write")
    p.add_argument("--mount", action="store_true", help="source is a --record recording of a still board while the "
                   "vehicle is turned by hand: find camera.mount (camera -> body) and write it into the -o camera "
                   "YAML, whose intrinsics it uses (companion/mountcal.py)")
    p.add_argument("--max-mount-residual", type=float, default=1.0, help="--mount: largest accepted residual, deg")
    p.set_defaults(func=_cmd_calibrate)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    if args.cols < 3 or args.rows < 3 or args.square <= 0 or args.every < 1:
        print("companion calibrate: --cols/--rows must be >= 3, --square > 0, --every >= 1", file=sys.stderr)
        return 2
    if args.board == "charuco" and not hasattr(cv2.aruco, args.dictionary):
        print(f"companion calibrate: --dictionary {args.dictionary}: not a cv2.aruco dictionary", file=sys.stderr)
        return 2
    board = Board(args.board, args.cols, args.rows, args.square, args.marker, args.dictionary)
    if args.mount:
        from companion.mountcal import cmd_mount

        return cmd_mount(args, board, Detector(board).find)
    try:
        views = collect(frames_from(args.source, args.max_frames, args.every), board)
        r = calibrate(views, args.min_views, args.min_coverage, args.max_error, args.min_tilt, args.min_fov)
    except CalibrationRefused as e:
        print(f"companion calibrate: refused: {e}", file=sys.stderr)
        return 2
    out = Path(args.output)
    out.write_text(camera_yaml(r, args.source), encoding="utf-8")
    K = r.K
    print(f"fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f} distortion "
          f"{', '.join(f'{d:.5f}' for d in r.dist)}")
    print(f"RMS reprojection error {r.rms:.3f} px, {r.views} views, coverage {r.coverage:.0%}; wrote {out} "
          f"(use: --config {out})")
    return 0
