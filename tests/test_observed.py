"""sim.observed: the observed clouds as spheres under the stability protocol.

Physics proved with physics: a ring resting on a rod (both seen only as surface points)
stays; the same ring beside the rod falls; bad clouds raise a clear error.
"""

import numpy as np
import pytest

from sim import kernels, observed

ROD_R, RING_R, TUBE_R = 0.005, 0.03, 0.004


def rod_cloud(n=1500, seed=0):
    """A horizontal rod along x (radius 5 mm, 20 cm long) seen from the front (y < 0 half and
    the top): points and outward normals."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.1, 0.1, n)
    a = rng.uniform(-np.pi, 0.35 * np.pi, n)  # the front half and over the top
    n_ = np.stack([np.zeros(n), np.cos(a), np.sin(a)], 1)
    return np.stack([x, np.zeros(n), np.zeros(n)], 1) + ROD_R * n_, n_


def ring_cloud(n=1500, seed=1):
    """A ring (torus: radius 3 cm, tube 4 mm) in the y-z plane around the object origin, seen
    from the front: points and outward normals (object frame)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(0, 2 * np.pi, n)  # around the ring
    v = rng.uniform(0, 2 * np.pi, n)  # around the tube
    centre = np.stack([np.zeros(n), RING_R * np.cos(u), RING_R * np.sin(u)], 1)
    radial = np.stack([np.zeros(n), np.cos(u), np.sin(u)], 1)
    normal = np.cos(v)[:, None] * radial + np.sin(v)[:, None] * np.array([1.0, 0, 0])
    pts = centre + TUBE_R * normal
    keep = pts[:, 1] < 0.02  # most of the front
    return pts[keep], normal[keep]


def clouds():
    op, on = ring_cloud()
    sp, sn = rod_cloud()
    return dict(object_points=op, object_normals=on, support_points=sp, support_normals=sn)


# The ring's top inner side rests on the rod: centre below the rod by R - tube - rod, 1 mm up.
HANGING = np.array([0.0, 0.0, -(RING_R - TUBE_R - ROD_R) + 0.001, 1, 0, 0, 0])
BESIDE = HANGING + np.array([0.2, 0, 0, 0, 0, 0, 0])  # 20 cm along the rod: past its end


def test_a_ring_on_a_rod_stays_and_beside_it_falls():
    status = observed.observed_stability(clouds(), np.stack([HANGING, BESIDE]), -0.5, None)
    assert status[0] == kernels.STABLE, kernels.STATUS_NAMES[status[0]]
    assert status[1] == kernels.FALLEN, kernels.STATUS_NAMES[status[1]]


def test_a_ring_through_the_rod_is_penetrating():
    inside = HANGING.copy()
    inside[2] = -RING_R + 0.001  # the ring's top tube 1 mm above the rod's axis: through it
    status = observed.observed_stability(clouds(), inside[None], -0.5, None)
    assert status[0] == kernels.PENETRATING


def test_first_staying_is_lazy_and_skips_a_faller():
    idx, status = observed.first_staying(clouds(), np.stack([BESIDE, HANGING, HANGING]), -0.5, None)
    assert idx == 1
    assert status.tolist() == [kernels.FALLEN, kernels.STABLE, -2]
    idx, status = observed.first_staying(clouds(), np.stack([BESIDE, BESIDE]), -0.5, None, top=1)
    assert idx == 0 and status.tolist() == [kernels.FALLEN, -2]


def test_bad_clouds_say_what_is_wrong():
    c = clouds()
    c["object_points"] = np.full_like(c["object_points"], np.nan)
    with pytest.raises(ValueError, match="object cloud: no finite point"):
        observed.observed_stability(c, HANGING[None], -0.5, None)
    c = clouds()
    c["support_normals"] = c["support_normals"][:10]
    with pytest.raises(ValueError, match="support cloud"):
        observed.observed_stability(c, HANGING[None], -0.5, None)
    with pytest.raises(ValueError, match="NaN"):
        observed.observed_stability(clouds(), np.full((1, 7), np.nan), -0.5, None)


def test_a_partly_nan_cloud_keeps_its_finite_points():
    c = clouds()
    c["object_points"] = c["object_points"].copy()
    c["object_points"][::7] = np.nan
    assert observed.observed_stability(c, HANGING[None], -0.5, None)[0] == kernels.STABLE


def test_the_pose_rotation_is_the_object_frame_s():
    """The same hang with the object's own frame turned: the clouds given in a frame rotated by
    R^T and the pose rotated by R put the same points in the same place, and the ring stays."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("xyz", [0.7, -0.4, 1.9])
    c = clouds()
    c["object_points"] = rot.inv().apply(c["object_points"])
    c["object_normals"] = rot.inv().apply(c["object_normals"])
    pose = HANGING.copy()
    pose[3:] = np.roll(rot.as_quat(), 1)  # wxyz
    assert observed.observed_stability(c, pose[None], -0.5, None)[0] == kernels.STABLE
    beside = pose + np.array([0.2, 0, 0, 0, 0, 0, 0])
    assert observed.observed_stability(c, beside[None], -0.5, None)[0] == kernels.FALLEN
