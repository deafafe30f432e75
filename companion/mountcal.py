"""``companion calibrate --mount``: how the camera sits on the body (camera -> body rotation) from a recording.

Record (``companion fly --record DIR``, or any recording with PX4's attitude in index.csv) a checkerboard (or
ChArUco board) that stays still in the world while the vehicle is turned by hand about at least two axes. Per
frame: the board's pose in the camera (corners as in ``companion calibrate``, then ``cv2.solvePnP`` with the
intrinsics of the camera YAML) and the vehicle's attitude body -> NED from the recording. Since the board does not
move, R_ned_body_i X R_cam_board_i is the same rotation for every frame; X = R_body_cam.

Solve: rotation-only hand-eye (eye-in-hand: the camera rides on the body, the board is still in the world).
``cv2.calibrateHandEye`` is not in the OpenCV 5 wheel this project uses (it moved out of calib3d), and it would
want the body's translations, which a recording does not have (PX4 has no good position while the vehicle is
carried indoors) and which do not matter for a rotation. So: Park's axis alignment as the start (each pair of
views: the body's relative rotation axis = X times the camera's; Wahba's problem, scipy's
``Rotation.align_vectors``), then alternating exact Procrustes steps on the board's world attitude and X. The
residual is the scatter of the board's world attitude R_ned_body_i X R_cam_board_i about its mean over all views
(RMS, deg): attitude errors, timing between frame and attitude, and lens errors all show up there.

A poor set is refused with the reason, one line: too few views with the board, too little rotation about a
second axis (rotations about one axis leave the mount free about that axis), or a residual too high. The mount
is written into the camera YAML (``camera.mount`` roll/pitch/yaw, deg), the rest of the file kept as it was.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from companion.frames import R_from_quat_wxyz

# Camera (OpenCV) -> body FRD of the zero mount: cam z -> body x, cam x -> body y, cam y -> body z
# (companion.config.CameraConfig.R_body_cam).
_BASE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
MAX_REPROJECTION_PX = 2.0  # a view whose board pose reprojects worse (blur, a wrong corner) is not used


class MountRefused(ValueError):
    """A set of views that would give a bad mount (one line: why)."""


@dataclass(frozen=True)
class MountResult:
    R_body_cam: np.ndarray  # camera (OpenCV) -> body FRD
    roll: float  # camera.mount angles, deg
    pitch: float
    yaw: float
    residual_deg: float  # RMS scatter of the board's world attitude over the views
    views: int
    spread_deg: tuple[float, float, float]  # std of the body's rotation about its principal axes, deg


def mount_angles(R_body_cam: np.ndarray) -> tuple[float, float, float]:
    """camera.mount (roll, pitch, yaw) deg of a camera -> body rotation (inverse of CameraConfig.R_body_cam)."""
    yaw, pitch, roll = Rotation.from_matrix(R_body_cam @ _BASE.T).as_euler("ZYX", degrees=True)
    return float(roll), float(pitch), float(yaw)


def rotation_spread(R_world_body: list[np.ndarray]) -> tuple[float, float, float]:
    """Std (deg) of the body attitudes about their mean, along the principal axes, largest first."""
    rots = Rotation.from_matrix(np.asarray(R_world_body))
    rv = (rots.mean().inv() * rots).as_rotvec()
    ev = np.sort(np.linalg.eigvalsh(np.cov(rv.T) if len(rv) > 1 else np.zeros((3, 3))))[::-1]
    s = np.degrees(np.sqrt(np.clip(ev, 0.0, None)))
    return float(s[0]), float(s[1]), float(s[2])


def _project_so3(M: np.ndarray) -> np.ndarray:
    """The rotation nearest M (Frobenius): SVD with the determinant fixed."""
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def _rotation_hand_eye(Rw: np.ndarray, Rc: np.ndarray, iterations: int = 50) -> np.ndarray:
    """X = R_body_cam with Rw[i] X Rc[i] = W (the board's fixed world attitude) for all i, least squares.

    Start: Park's axis alignment. Every pair of views i < j gives A X = X B with A = Rw[j]^T Rw[i] (the body's
    motion) and B = Rc[j] Rc[i]^T (the camera's), so rotvec(A) = X rotvec(B): Wahba's problem, solved by
    scipy's Rotation.align_vectors. Then alternate the two Procrustes steps of min sum |Rw[i] X Rc[i] - W|^2
    (W given X, X given W), each exact, so the cost never rises.
    """
    i, j = np.triu_indices(len(Rw), 1)
    a = Rotation.from_matrix(np.einsum("nji,njk->nik", Rw[j], Rw[i])).as_rotvec()
    b = Rotation.from_matrix(np.einsum("nij,nkj->nik", Rc[j], Rc[i])).as_rotvec()
    X = Rotation.align_vectors(a, b)[0].as_matrix()
    for _ in range(iterations):
        W = _project_so3(np.einsum("nij,jk,nkl->il", Rw, X, Rc))
        X_new = _project_so3(np.einsum("nji,jk,nlk->il", Rw, W, Rc))
        done = np.abs(X_new - X).max() < 1e-12
        X = X_new
        if done:
            break
    return X


def solve_mount(R_world_body: list[np.ndarray], R_cam_board: list[np.ndarray], *, min_views: int = 10,
                min_spread: float = 4.0, max_residual: float = 1.0) -> MountResult:
    """Camera -> body rotation from per-view body attitudes (body -> world) and board poses (board -> camera)."""
    n = len(R_world_body)
    if n != len(R_cam_board):
        raise ValueError(f"solve_mount: {n} attitudes but {len(R_cam_board)} board poses")
    if n < max(min_views, 3):
        raise MountRefused(f"too few views with the board: {n} (need {max(min_views, 3)}); record longer, board "
                           f"fully in view")
    spread = rotation_spread(R_world_body)
    if spread[1] < min_spread:
        raise MountRefused(
            f"too little rotation diversity: the body turned {spread[0]:.1f} / {spread[1]:.1f} / {spread[2]:.1f} "
            f"deg (std about its principal axes); need >= {min_spread:g} deg about at least two axes (turn it in "
            f"roll, pitch and yaw)")
    R_body_cam = _rotation_hand_eye(np.asarray(R_world_body, float), np.asarray(R_cam_board, float))
    boards = Rotation.from_matrix(np.einsum("nij,jk,nkl->nil", np.asarray(R_world_body), R_body_cam,
                                            np.asarray(R_cam_board)))
    err = np.linalg.norm((boards.mean().inv() * boards).as_rotvec(), axis=1)
    residual = math.degrees(float(np.sqrt(np.mean(err**2))))
    if not residual <= max_residual:
        raise MountRefused(f"residual {residual:.2f} deg over {n} views exceeds {max_residual:g} deg (attitude not "
                           f"matching the frames: recording timing, a moving board, or wrong intrinsics)")
    roll, pitch, yaw = mount_angles(R_body_cam)
    return MountResult(R_body_cam, roll, pitch, yaw, residual, n, spread)


def board_views(folder: str | Path, board: Any, K: np.ndarray, dist: np.ndarray,
                find_board: Callable[[np.ndarray], Any] | None = None
                ) -> tuple[list[np.ndarray], list[np.ndarray], int]:
    """(body -> NED attitudes, board -> camera rotations, frames read) of the recording's frames that show the
    board and have an attitude. ``board``: companion.calibrate.Board; ``find_board``: its Detector's ``find``
    (used for ChArUco; a checkerboard is found here, faster)."""
    from companion.app.record import RecordingReader

    reader = RecordingReader(folder)
    find = _find_checkerboard if board.kind == "checkerboard" else None
    if find is None and find_board is None:
        raise ValueError(f"board_views: a {board.kind} board needs its finder (companion.calibrate.Detector.find)")
    R_wb: list[np.ndarray] = []
    R_cb: list[np.ndarray] = []
    k = 0
    while True:
        ok, img = reader.read()
        if not ok:
            break
        q = reader.q[k]
        k += 1
        if img is None or not np.isfinite(q).all():
            continue
        found = find(board, img) if find is not None else find_board(img)  # type: ignore[misc]
        if found is None:
            continue
        obj, pts = found
        ok, rvec, tvec = cv2.solvePnP(obj, pts, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            continue
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        if float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - pts) ** 2, axis=1)))) > MAX_REPROJECTION_PX:
            continue
        R_wb.append(R_from_quat_wxyz(q))
        R_cb.append(cv2.Rodrigues(rvec)[0])
    return R_wb, R_cb, k


def _find_checkerboard(board: Any, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Checkerboard corners: cv2.findChessboardCorners + cornerSubPix (~10x faster than the sector-based finder
    ``companion calibrate`` uses for intrinsics, as accurate on a sharp board; a recording has hundreds of frames)."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    pattern = (board.cols - 1, board.rows - 1)
    ok, corners = cv2.findChessboardCorners(gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                            | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK)
    if not ok:
        return None
    corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3))
    return board.object_points(), corners.reshape(-1, 2).astype(np.float32)


# ------------------------------------------------------------------------------------------------ the YAML


def write_mount(path: str | Path, r: MountResult, source: str) -> None:
    """Set ``camera.mount`` in a camera YAML, keeping every other line (and comment) of the file."""
    path = Path(path)
    text = path.read_text(encoding="utf-8") if path.exists() else ""
    mount = (f"mount: {{roll: {r.roll:.3f}, pitch: {r.pitch:.3f}, yaw: {r.yaw:.3f}}}  # companion calibrate "
             f"--mount {source}: residual {r.residual_deg:.2f} deg, {r.views} views")
    lines = text.splitlines()
    cam = next((i for i, ln in enumerate(lines) if re.match(r"camera:\s*(#.*)?$", ln)), None)
    if cam is None:
        if any(re.match(r"camera:", ln) for ln in lines):
            raise ValueError(f"{path}: its camera section is not a block (camera: on a line of its own); "
                             f"set camera.mount by hand: roll {r.roll:.3f}, pitch {r.pitch:.3f}, yaw {r.yaw:.3f}")
        lines += ["camera:", "  " + mount]
    else:
        # The camera block: the lines after "camera:" that are indented (or blank/comments inside it).
        end = cam + 1
        while end < len(lines) and (lines[end].startswith((" ", "\t")) or not lines[end].strip()):
            end += 1
        block = lines[cam + 1:end]
        indent = next((ln[: len(ln) - len(ln.lstrip())] for ln in block if ln.strip()), "  ")
        out, skip = [], False
        for ln in block:
            if skip and (not ln.strip() or len(ln) - len(ln.lstrip()) > len(indent)):
                continue  # the old mount's nested keys
            skip = False
            if ln.startswith(indent + "mount:"):
                skip = ln.strip() == "mount:" or ln.split("#")[0].strip() == "mount:"
                continue
            out.append(ln)
        lines = [*lines[:cam + 1], indent + mount, *out, *lines[end:]]
    new = "\n".join(lines) + "\n"
    data = yaml.safe_load(new)  # what we wrote must read back as exactly this mount
    m = data["camera"]["mount"]
    if (m["roll"], m["pitch"], m["yaw"]) != (round(r.roll, 3), round(r.pitch, 3), round(r.yaw, 3)):
        raise ValueError(f"{path}: could not set camera.mount in this file's layout; set it by hand")
    path.write_text(new, encoding="utf-8")


# ------------------------------------------------------------------------------------------------ CLI


def cmd_mount(args: Any, board: Any, find_board: Callable[[np.ndarray], Any]) -> int:
    """``companion calibrate REC --mount -o CAMERA.yaml``: intrinsics from CAMERA.yaml, the mount written back."""
    from companion.app.record import RecordError, is_recording
    from companion.config import load_config
    from companion.configbase import ConfigError

    name = "companion calibrate --mount"
    if not is_recording(args.source):
        print(f"{name}: {args.source}: not a recording (no index.csv); record with --record DIR", file=sys.stderr)
        return 2
    out = Path(args.output)
    if not out.is_file():
        print(f"{name}: -o {out}: no such camera YAML; the mount needs the camera's intrinsics (run companion "
              f"calibrate on board views with -o {out} first, or give the YAML your flights use)", file=sys.stderr)
        return 2
    try:
        camera = load_config([out]).camera
    except (ConfigError, OSError, ValueError) as e:
        print(f"{name}: {out}: {e}", file=sys.stderr)
        return 2
    try:
        R_wb, R_cb, frames = board_views(args.source, board, camera.K, camera.dist, find_board)
        r = solve_mount(R_wb, R_cb, min_views=args.min_views, max_residual=args.max_mount_residual)
    except MountRefused as e:
        print(f"{name}: refused: {e}", file=sys.stderr)
        return 2
    except RecordError as e:
        print(f"{name}: {e}", file=sys.stderr)
        return 2
    try:
        write_mount(out, r, str(args.source))
    except (OSError, ValueError) as e:
        print(f"{name}: {e}", file=sys.stderr)
        return 2
    print(f"mount roll {r.roll:.2f} pitch {r.pitch:.2f} yaw {r.yaw:.2f} deg, residual {r.residual_deg:.2f} deg, "
          f"{r.views} of {frames} frames; body turned {r.spread_deg[0]:.0f}/{r.spread_deg[1]:.0f}/"
          f"{r.spread_deg[2]:.0f} deg (std); wrote camera.mount into {out}")
    return 0
