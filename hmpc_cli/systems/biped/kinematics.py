"""The biped's link geometry in plain NumPy: the leaf that params, terrain and model share.

Point and centre-of-mass coefficients of the five links (see :mod:`.model` for the
convention) and the swing foot's position, from any object with the link lengths,
centres of mass, masses and inertias of :class:`.params.BipedParams` (a :class:`Links`).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class Links(Protocol):
    """The link data the geometry reads.

    Lengths and CoM offsets [m], masses [kg], inertias [kg m^2], a mass scale.
    """

    calf_length: float
    thigh_length: float
    torso_length: float
    calf_com: float
    thigh_com: float
    torso_com: float
    calf_mass: float
    thigh_mass: float
    torso_mass: float
    calf_inertia: float
    thigh_inertia: float
    torso_inertia: float
    mass_scale: float


N_Q = 5
STANCE_X = 2 * N_Q  #: index of the stance-foot x in the state (the stance-foot y follows)
#: names of the points returned by :attr:`BipedModel.points` (columns, in this order)
POINT_NAMES = ("stance_foot", "stance_knee", "hip", "torso_top", "swing_knee", "swing_foot")


def link_geometry(p: Links) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients D (points x links), C (bodies x links), masses and inertias."""
    lc, lt, lT = p.calf_length, p.thigh_length, p.torso_length
    d = np.array([[0, 0, 0, 0, 0], [lc, 0, 0, 0, 0], [lc, lt, 0, 0, 0], [lc, lt, lT, 0, 0],
                  [lc, lt, 0, -lt, 0], [lc, lt, 0, -lt, -lc]], dtype=float)
    c = np.array([[lc - p.calf_com, 0, 0, 0, 0],           # stance calf: calf_com from knee
                  [lc, lt - p.thigh_com, 0, 0, 0],         # stance thigh: thigh_com from hip
                  [lc, lt, p.torso_com, 0, 0],             # torso
                  [lc, lt, 0, -p.thigh_com, 0],            # swing thigh
                  [lc, lt, 0, -lt, -p.calf_com]], dtype=float)  # swing calf
    s = p.mass_scale
    mass = s * np.array([p.calf_mass, p.thigh_mass, p.torso_mass, p.thigh_mass, p.calf_mass])
    inertia = s * np.array([p.calf_inertia, p.thigh_inertia, p.torso_inertia,
                            p.thigh_inertia, p.calf_inertia])
    return d, c, mass, inertia


def swing_foot_numeric(p: Links, q) -> np.ndarray:
    """Swing foot relative to the stance foot for angles q (NumPy, used by validation)."""
    d = link_geometry(p)[0]
    theta = np.cumsum(np.asarray(q, dtype=float))
    return np.array([-d[-1] @ np.sin(theta), d[-1] @ np.cos(theta)])
