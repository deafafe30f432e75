"""The demand scale at a tiny thrust floor (issue 22): with thrust_min <= 1e-5 in exact FOV mode a third of
saturated demands got scale 0 where up to 0.85 was feasible (rounding at the floor made the tilt room -inf,
and the root finder stopped at once). The feasible scales form an interval [0, s*] (companion/guidance.py):
s is s* when s is feasible and s + 1e-6 is not."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import load_config
from companion.configbase import ConfigError
from companion.guidance import G, GuidanceParams, _best_tx, demand_scale


@pytest.mark.parametrize("thrust_min", [1e-5, 1e-6, 0.01, 0.1])
def test_demand_scale_is_the_largest_feasible_at_any_thrust_floor(thrust_min):
    p = GuidanceParams(k_pn=3.0, v_rel_bar=5.0, gamma_bar=math.radians(30.0), f_max=2.0 * G,
                       f_min=G * thrust_min / 0.5, fov="exact", max_tilt=math.radians(50.0))
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(150):
        tilt, el = rng.uniform(-0.6, 0.6), rng.uniform(-0.5, 0.5)
        g_y, g_z = -0.3 * G * math.sin(tilt), -G * math.cos(el)  # gravity in the PN frame
        u = (math.sin(el), 0.0, math.cos(el))  # world up in the PN frame
        a_y, a_z = rng.normal(0.0, 25.0, 2)  # large: most demands saturate

        def feasible(s: float, a_y=a_y, a_z=a_z, g_y=g_y, g_z=g_z, u=u) -> bool:
            return _best_tx(s * a_y - g_y, s * a_z - g_z, u, p) is not None

        s = demand_scale(a_y, a_z, g_y, g_z, p, u)
        if s is None or s >= 1.0:
            continue
        checked += 1
        assert feasible(s), (a_y, a_z, s)
        assert not feasible(s + 1e-6), f"scale {s} but {s + 1e-6} is feasible (a = {a_y:.2f}, {a_z:.2f})"
    assert checked > 100  # saturated demands were checked, not skipped


def test_config_bounds_thrust_min():
    with pytest.raises(ConfigError, match="thrust_min"):
        load_config([], ["airframe.thrust_min=1e-5"])
    assert load_config([], ["airframe.thrust_min=0.01"]).airframe.thrust_min == 0.01
