"""The per-frame fast paths of issue 21 item 3 return the same floats, bit for bit, as the code they replace
(the suites' results must not move): each is checked against the array / stdlib form it stands in for."""

from __future__ import annotations

import dataclasses
import math
import struct

import numpy as np
import pytest

from companion import guidance
from companion.frames import R_from_quat_wxyz, R_from_quat_wxyz_shared, euler_ned_deg_from_R, euler_ned_deg_from_rows
from perception.los import CameraModel, LosFilter

RNG = np.random.default_rng(21)


def _camera(dist: list[float] | None = None) -> CameraModel:
    K = np.array([[410.0, 0.0, 321.3], [0.0, 405.5, 238.7], [0.0, 0.0, 1.0]])
    return CameraModel(K, np.array(dist or []), np.eye(3), 640, 480)


@pytest.mark.parametrize("dist", [None, [-0.1, 0.02, 0.0, 0.0, 0.0]])
def test_ray_cam_xyz_is_ray_cam(dist: list[float] | None) -> None:
    cam = _camera(dist)
    K_inv = np.linalg.inv(cam.K)
    for u, v in RNG.uniform([-50, -50], [700, 530], size=(300, 2)):
        xyz = cam.ray_cam_xyz(float(u), float(v))
        assert np.array(xyz).tobytes() == cam.ray_cam(float(u), float(v)).tobytes()
        if dist is None:  # the old array form, written out
            x = K_inv[0, 0] * u + K_inv[0, 1] * v + K_inv[0, 2]
            y = K_inv[1, 1] * v + K_inv[1, 2]
            old = np.array([x, y, 1.0]) / math.sqrt(x * x + y * y + 1.0)
            assert np.array(xyz).tobytes() == old.tobytes()


def test_los_filter_scalar_equals_array_form() -> None:
    f = LosFilter(3.0)
    value = None
    for k in range(300):
        l = RNG.normal(size=3)  # noqa: E741
        l = l / np.linalg.norm(l)  # noqa: E741
        t = k / 30.0
        out = f.update(t, l)
        if value is None:
            value = l.copy()
        else:
            alpha = 1.0 - math.exp(-2.0 * math.pi * 3.0 * (t - (k - 1) / 30.0))
            v = value + alpha * (l - value)
            value = v / math.sqrt(float(v @ v))
        # The blend is element-wise, the same bits; the norm is a dot product, which numpy's BLAS fuses into
        # multiply-adds on some CPUs (OpenBLAS's SkylakeX kernel: AVX-512 machines) and not on others, so the
        # scalar sum of squares can differ from it in the last bits there.
        np.testing.assert_array_max_ulp(out, value, maxulp=4)
        value = out.copy()  # go on from the filter's own state: the next step is compared from the same input


def test_los_rate_vector_is_lambda_dot_n() -> None:
    for _ in range(500):
        a, b = RNG.normal(size=3), RNG.normal(size=3)
        a /= np.linalg.norm(a)
        b = a + RNG.uniform(1e-9, 0.3) * b
        b /= np.linalg.norm(b)
        dt = float(RNG.uniform(0.01, 0.1))
        r = guidance.los_rate(a, b, dt)
        assert np.array(guidance.los_rate_vector(a, b, dt)).tobytes() == (r.lambda_dot * r.n).tobytes()
    assert guidance.los_rate_vector(a, None, 0.03) == (0.0, 0.0, 0.0)
    assert guidance.los_rate_vector(a, a, 0.03) == (0.0, 0.0, 0.0)


def test_with_gamma_bar_is_replace() -> None:
    gp = guidance.GuidanceParams(k_pn=3.0, v_rel_bar=15.0, gamma_bar=0.3, f_max=19.6, f_min=1.0)
    q = guidance.with_gamma_bar(gp, 0.1)
    assert q == dataclasses.replace(gp, gamma_bar=0.1)
    assert gp.gamma_bar == 0.3
    with pytest.raises(ValueError, match="gamma_bar"):
        guidance.with_gamma_bar(gp, -0.1)


def test_euler_rows_and_quat_cache() -> None:
    for _ in range(300):
        q = RNG.normal(size=4)
        R = R_from_quat_wxyz(q)
        R2 = R_from_quat_wxyz(q)  # the cached one: equal, not the same object
        assert R2.tobytes() == R.tobytes() and R2 is not R
        R2[0, 0] = 7.0
        assert R_from_quat_wxyz(q).tobytes() == R.tobytes()  # a caller's edit does not reach the cache
        assert R_from_quat_wxyz(list(q)).tobytes() == R.tobytes()
        shared = R_from_quat_wxyz_shared(q)  # the controller's: the cached matrix itself, which nobody can change
        assert shared.tobytes() == R.tobytes() and not shared.flags.writeable
        assert R_from_quat_wxyz(q).flags.writeable
        # the old element-wise form
        w, x, y, z = (float(c) for c in q)
        s = 2.0 / (w * w + x * x + y * y + z * z)
        assert R[1, 2] == s * (y * z - x * w) and R[2, 0] == s * (x * z - y * w)
        assert euler_ned_deg_from_rows(R.tolist()) == euler_ned_deg_from_R(R)
    assert R_from_quat_wxyz(-0.0 * np.array([1.0, 1.0, 1.0, 1.0]) + np.array([1.0, 0.0, 0.0, 0.0])) is not None


def test_to_setpoint_rows_match_array_form() -> None:
    from scipy.spatial.transform import Rotation

    for _ in range(200):
        R_W_B = Rotation.random(random_state=int(RNG.integers(1 << 30))).as_matrix()
        sp = guidance.to_setpoint(R_W_B, 9.0, 0.5, 0.05)
        old = R_W_B[[1, 0, 2]] * np.outer([1.0, 1.0, -1.0], [1.0, -1.0, -1.0])
        assert sp.R_ned_frd.tobytes() == old.tobytes()
        assert (sp.roll_deg, sp.pitch_deg, sp.yaw_deg) == euler_ned_deg_from_R(old)


def test_swap_ned_enu_is_the_matrix_product() -> None:
    """P_NED_ENU.dot(v) and swap_ned_enu(v): the same bits, zeros of either sign, infinities and NaN included."""
    from companion.frames import P_NED_ENU, swap_ned_enu

    special = [0.0, -0.0, 1.0, -1.0, math.inf, -math.inf, math.nan, 1e-300, -2.5e300]
    vecs = [np.array([a, b, c]) for a in special for b in special for c in special]
    vecs += list(RNG.normal(size=(500, 3)) * RNG.choice([1e-8, 1.0, 1e8], size=(500, 1)))
    for v in vecs:
        with np.errstate(invalid="ignore"):  # 0 * inf in the matrix products
            got, ref, ref2 = swap_ned_enu(v), P_NED_ENU.dot(v), P_NED_ENU @ v
        assert ref.tobytes() == ref2.tobytes(), v
        nan = np.isnan(ref)
        # A NaN stays a NaN (its sign bit is the BLAS kernel's and nothing reads it); every other value bit for bit.
        assert (np.isnan(got) == nan).all() and got[~nan].tobytes() == ref[~nan].tobytes(), v


def test_dot_method_is_the_matmul_operator() -> None:
    """The per-frame path calls ndarray.dot, not ``@`` (numpy's matmul dispatch costs 2-4x on 3-vectors): the same
    BLAS result, bit for bit, for every shape it is used with; and sqrt(v.dot(v)) is np.linalg.norm(v)."""
    for _ in range(2000):
        R, M = RNG.normal(size=(3, 3)), RNG.normal(size=(3, 3))
        v, w = RNG.normal(size=3), RNG.normal(size=3)
        assert R.dot(v).tobytes() == (R @ v).tobytes()
        assert R.T.dot(v).tobytes() == (R.T @ v).tobytes()
        assert R.dot(M).tobytes() == (R @ M).tobytes()
        assert R[:, 1].dot(v) == R[:, 1] @ v
        assert float(v.dot(w)) == float(v @ w)
        assert math.sqrt(v.dot(v)) == float(np.linalg.norm(v))
    for n in (4, 9, 16, 40):  # the barometric window's slope
        a, b = RNG.normal(size=n), RNG.normal(size=n)
        assert float(a.dot(b)) == float(a @ b)
    # The simulated camera's shapes: a transposed product, the rim basis through it, the rim samples, K's view.
    K2T = np.array([[410.0, 0.0, 321.3], [0.0, 405.5, 238.7]])[:2, :2].T
    for _ in range(500):
        R, M, v = RNG.normal(size=(3, 3)), RNG.normal(size=(3, 3)), RNG.normal(size=3)
        Rc = (R @ M).T
        assert Rc.tobytes() == R.dot(M).T.tobytes() and (Rc @ v).tobytes() == Rc.dot(v).tobytes()
        ab = RNG.normal(size=(2, 3))
        assert (ab @ Rc.T).tobytes() == ab.dot(Rc.T).tobytes()
        for n in (32, 128):
            cs = RNG.normal(size=(n, 2))
            assert (cs @ ab).tobytes() == cs.dot(ab).tobytes()
            assert (cs @ K2T).tobytes() == cs.dot(K2T).tobytes()


def test_flat_reshaped_rotation_is_the_nested_one() -> None:
    from companion.frames import R_from_quat_wxyz as rq

    for _ in range(300):
        w, x, y, z = RNG.normal(size=4).tolist()
        s = 2.0 / (w * w + x * x + y * y + z * z)
        nested = np.array([
            [1.0 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
            [s * (x * y + z * w), 1.0 - s * (x * x + z * z), s * (y * z - x * w)],
            [s * (x * z - y * w), s * (y * z + x * w), 1.0 - s * (x * x + y * y)],
        ])
        R = rq(np.array([w, x, y, z]))
        assert R.tobytes() == nested.tobytes() and R.flags.c_contiguous
        assert R.dot(np.array([0.3, -0.2, 0.9])).tobytes() == (nested @ np.array([0.3, -0.2, 0.9])).tobytes()


def test_ray_body_of_an_axis_mount_is_the_matrix_product() -> None:
    """A mount that permutes and negates axes takes ray_body's scalar path: the same bits as the matrix product;
    a tilted mount keeps the matrix product."""
    mounts = [np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
              np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), np.eye(3)]
    K = np.array([[410.0, 0.0, 321.3], [0.0, 405.5, 238.7], [0.0, 0.0, 1.0]])
    for R in mounts:
        cam = CameraModel(K, np.array([]), R, 640, 480)
        assert cam._perm_rows is not None
        for u, v in [(321.3, 238.7), (0.0, 0.0), *RNG.uniform([-50, -50], [700, 530], size=(300, 2)).tolist()]:
            assert cam.ray_body(u, v).tobytes() == R.dot(cam.ray_cam(u, v)).tobytes()
    c, s = math.cos(0.26), math.sin(0.26)
    tilted = CameraModel(K, np.array([]), np.array([[0.0, s, c], [1.0, 0.0, 0.0], [0.0, c, -s]]), 640, 480)
    assert tilted._perm_rows is None


def test_cross_xyz_is_np_cross() -> None:
    from companion.frames import cross_xyz

    special = [0.0, -0.0, 1.0, -1.0, 0.3]
    pairs = [(np.array([a, b, c]), np.array([c, a, b])) for a in special for b in special for c in special]
    pairs += [(RNG.normal(size=3), RNG.normal(size=3)) for _ in range(1000)]
    for a, b in pairs:
        assert np.array(cross_xyz(a.tolist(), b.tolist())).tobytes() == np.cross(a, b).tobytes(), (a, b)


@pytest.mark.parametrize("dist", [None, [-0.1, 0.02, 0.0, 0.0, 0.0]])
def test_ray_angle_is_the_angle_of_the_rays(dist: list[float] | None) -> None:
    """CameraModel.ray_angle (the closing-speed range's two angles a frame) is atan2(|a x b|, a . b) of the two
    ray_cam_xyz rays, bit for bit."""
    cam = _camera(dist)
    for u0, v0, u1, v1 in RNG.uniform([-50, -50, -50, -50], [700, 530, 700, 530], size=(300, 4)).tolist():
        (ax, ay, az), (bx, by, bz) = cam.ray_cam_xyz(u0, v0), cam.ray_cam_xyz(u1, v1)
        cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        assert cam.ray_angle(u0, v0, u1, v1) == math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz),
                                                            ax * bx + ay * by + az * bz)


def test_one_array_of_two_factors_gives_the_same_product() -> None:
    """solve multiplies R_W_PN by R_y(phi) R_x(theta) as the two halves of one (2, 3, 3) array: BLAS gets the same
    operands and gives the same product as from two arrays, bit for bit (signed zeros included)."""
    for _ in range(3000):
        A, B = RNG.normal(size=(3, 3)), RNG.normal(size=(3, 3))
        A[RNG.integers(3), RNG.integers(3)] = 0.0
        B[RNG.integers(3), RNG.integers(3)] = -0.0
        M = np.array((*A.ravel().tolist(), *B.ravel().tolist())).reshape(2, 3, 3)
        assert M[0].dot(M[1]).tobytes() == A.dot(B).tobytes()
        # solve's own construction: an immutable array on the packed floats
        P = np.ndarray((2, 3, 3), np.float64, struct.pack("18d", *A.ravel().tolist(), *B.ravel().tolist()))
        assert P[0].dot(P[1]).tobytes() == A.dot(B).tobytes()
    gp = guidance.GuidanceParams(k_pn=3.0, v_rel_bar=15.0, gamma_bar=0.3, f_max=19.6, f_min=1.0)
    for _ in range(300):
        los = RNG.normal(size=3) * (1.0, 1.0, 0.3)
        los /= np.linalg.norm(los)
        sol = guidance.solve(los, RNG.normal(size=3) * 5.0, gp)
        R = guidance.pn_frame(los).dot(guidance._R_y_R_x(sol.phi, sol.theta))
        assert sol.R_W_B.tobytes() == R.tobytes()


@pytest.mark.parametrize("fov", ["exact", "paper"])
def test_best_tx_plain_is_the_envelope_path(fov: str) -> None:
    """solve's _best_tx_plain (no uptilt: the one piece written out) gives _best_tx's t_x or None, bit for bit, over
    feasible and infeasible thrusts, every tilt-cone case (H inside, the root, the maximiser, no t_x) included."""
    hits = {"H": 0, "root": 0, "none": 0}
    for _ in range(20000):
        gp = guidance.GuidanceParams(k_pn=3.0, v_rel_bar=15.0, gamma_bar=float(RNG.uniform(0.05, 1.5)),
                                     f_max=19.62, f_min=float(RNG.choice([1e-5, 1.962, 5.0])), fov=fov,
                                     max_tilt=float(RNG.uniform(0.05, 1.5)))
        u = RNG.normal(size=3)
        u = tuple((u / np.linalg.norm(u)).tolist())
        if RNG.random() < 0.05:
            u = (float(RNG.choice([0.0, -0.0])), 0.0, 1.0)  # LOS level: the maximiser at 0
        t_y, t_z = RNG.normal(0.0, 8.0), RNG.uniform(-2.0, 22.0)
        if RNG.random() < 0.05:
            t_y = float(RNG.choice([0.0, -0.0]))
        new, old = guidance._best_tx_plain(t_y, t_z, u, gp), guidance._best_tx(t_y, t_z, u, gp)
        assert (new is None and old is None) or np.float64(new).tobytes() == np.float64(old).tobytes()
        e = guidance._envelope(t_y, t_z, u, gp)
        hits["none" if old is None else "H" if e is not None and old == e[0][0][1] else "root"] += 1
    assert min(hits.values()) > 100, hits
