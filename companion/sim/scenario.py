"""Initial conditions of one run (paper V-A), drawn from a seed.

Geometry (decisions where the paper is silent):
* the vehicle starts at (0, 0, h), h ~ U(altitude_min, altitude_max) AGL;
* the gate starts at horizontal distance D ~ U(distance_min, distance_max) in a random bearing,
  its centre +-gate_height_offset from h; its opening faces the vehicle (normal horizontal,
  pointing back at the start);
* the initial velocity has the configured speed (10 m/s), horizontal, turned by
  alpha ~ U(-angle_max, angle_max) from the LOS bearing;
* the start attitude is the cruise trim for that velocity: thrust axis along g + drag, camera
  (body x) yawed at the gate, so the first frame sees it; thrust at the trim value;
* gate motions per companion/sim/gates.py (linear: sideways in the gate plane, random sign;
  planar/knot: random start phase, the trajectory placed through the gate's start position);
* a target standing on the ground (``sim.target.on_ground``) has its centre at half its height above z = 0
  instead (the draw of the height offset is still made, so other draws do not shift).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from companion.frames import cross_xyz
from companion.sim.dynamics import G, QuadParams, QuadState
from companion.sim.gates import GateMotion, MotionKind, make_gate


@dataclass(frozen=True)
class Scenario:
    state0: QuadState
    gate: GateMotion
    distance: float  # m, initial horizontal distance to the gate
    angle: float  # deg, initial velocity vs LOS bearing
    altitude: float  # m, start altitude


def cruise_attitude(v_enu: np.ndarray, heading_enu: np.ndarray, params: QuadParams) -> tuple[np.ndarray, float]:
    """(q xyzw, mass-normalised thrust) that holds velocity v against drag and gravity, body x toward heading."""
    # Once a run, but ~1 % of a simulated frame: np.linalg.norm of a vector is sqrt(v.dot(v)), its own formula, and
    # np.cross is cross_xyz's element-wise formula; the same bits without their wrappers.
    v = np.asarray(v_enu, float)
    speed = math.sqrt(v.dot(v))
    drag_acc = (params.drag_lin + params.drag_quad * speed) * v / params.mass
    thrust_vec = drag_acc + np.array([0.0, 0.0, G])
    f = math.sqrt(thrust_vec.dot(thrust_vec))
    z = thrust_vec / f
    heading = np.asarray(heading_enu, float)
    x = heading - heading.dot(z) * z
    x /= math.sqrt(x.dot(x))
    y = np.array(cross_xyz(z.tolist(), x.tolist()))
    return Rotation.from_matrix(np.column_stack((x, y, z))).as_quat(), f


def make_scenario(
    motion: MotionKind,
    rng: np.random.Generator,
    scenario_cfg: object,
    gates_cfg: object,
    params: QuadParams,
    ground_centre: float | None = None,
) -> Scenario:
    """Draw one initial condition. ``scenario_cfg``/``gates_cfg``: ScenarioConfig / GateMotionConfig;
    ``ground_centre``: the target stands on the ground with its centre this high (m), else None."""
    sc = scenario_cfg
    if sc.distance_max < sc.distance_min or sc.altitude_max < sc.altitude_min:
        raise ValueError("sim.scenario: *_max must be >= *_min")
    d = float(rng.uniform(sc.distance_min, sc.distance_max))
    h = float(rng.uniform(sc.altitude_min, sc.altitude_max))
    bearing = float(rng.uniform(0.0, 2 * math.pi))
    dz = float(rng.uniform(-sc.gate_height_offset, sc.gate_height_offset))
    alpha = float(rng.uniform(-sc.angle_max, sc.angle_max))
    e = np.array([math.cos(bearing), math.sin(bearing), 0.0])
    p_vehicle = np.array([0.0, 0.0, h])
    p_gate = p_vehicle + d * e + np.array([0.0, 0.0, dz])
    if ground_centre is not None:
        p_gate[2] = ground_centre
    gate = make_gate(motion, p_gate, -e, rng=rng, gates_cfg=gates_cfg)
    b = bearing + math.radians(alpha)
    v0 = sc.speed * np.array([math.cos(b), math.sin(b), 0.0])
    los = p_gate - p_vehicle
    q0, f0 = cruise_attitude(v0, los / np.linalg.norm(los), params)
    state = QuadState(t=0.0, p=p_vehicle, v=v0, q=q0, f_th=min(f0, params.f_max), on_ground=False)
    return Scenario(state, gate, d, alpha, h)
