"""Synthetic flows and seeding: analytic properties, advection accuracy, particle counts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plenopiv.errors import ConfigError
from plenopiv.synthetic.flows import HillVortex, LambOseen, Uniform, advect
from plenopiv.synthetic.seeding import SeedingBox, particle_count, random_particles


def divergence(flow, points, h=1e-7):
    div = np.zeros(len(points))
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = h
        div += (flow(points + e)[:, axis] - flow(points - e)[:, axis]) / (2 * h)
    return div


def test_lamb_oseen_profile_and_direction():
    gamma, rc = 2e-3, 1.5e-3
    flow = LambOseen(circulation=gamma, core_radius=rc, axis=(0, 1, 0))
    p = np.array([[rc, 0.3e-3, 0.0], [0.0, -1e-3, 2 * rc]])
    v = flow(p)
    expect = gamma / (2 * math.pi * rc) * (1 - math.exp(-1))
    assert np.linalg.norm(v[0]) == pytest.approx(expect, rel=1e-12)
    # azimuthal: no axial and no radial component
    assert np.allclose(v[:, 1], 0) and abs(v[0] @ [1, 0, 0]) < 1e-15
    assert flow(np.zeros((1, 3))) == pytest.approx(np.zeros((1, 3)))
    # axis along y: motion in depth (z) at x = r_c
    assert abs(v[0, 2]) > 0


def test_flows_are_divergence_free(rng):
    pts = rng.uniform(-4e-3, 4e-3, (200, 3))
    oseen = LambOseen(circulation=1e-3, core_radius=1e-3, axis=(1, 2, 0.5))
    hill = HillVortex(radius=3e-3, speed=0.2)
    for flow in (oseen, hill):
        scale = np.abs(flow(pts)).max() / 1e-3          # |v| / length scale
        assert np.abs(divergence(flow, pts)).max() < 1e-5 * scale


def test_hill_vortex_continuity_and_far_field():
    a, u = 3e-3, 0.2
    hill = HillVortex(radius=a, speed=u, axis=(0, 0, 1))
    dirs = np.array([[1, 0, 0], [0.6, 0, 0.8], [0, 0.8, -0.6]], float)
    inside, outside = hill(dirs * a * (1 - 1e-9)), hill(dirs * a * (1 + 1e-9))
    assert np.allclose(inside, outside, atol=1e-7 * u)
    assert hill(np.zeros((1, 3)))[0] == pytest.approx([0, 0, 1.5 * u])
    # the vortex ring: fluid at rest (vortex frame) at ρ = a/√2 in the mid plane
    assert np.allclose(hill(np.array([[a / math.sqrt(2), 0, 0]])), 0, atol=1e-15)
    far = hill(np.array([[0.0, 0.0, 1e3 * a]]))[0]
    assert far == pytest.approx([0, 0, -u], rel=1e-6)
    lab = HillVortex(radius=a, speed=u, axis=(0, 0, 1), frame="lab")
    assert np.allclose(lab(np.array([[0.0, 0.0, 1e3 * a]])), 0, atol=1e-8 * u)


def test_rk4_advection_keeps_oseen_orbits_circular():
    flow = LambOseen(circulation=3e-3, core_radius=1e-3, axis=(0, 0, 1))
    p0 = np.array([[1e-3, 0, 0], [0, 2.5e-3, 1e-3]])
    v = np.linalg.norm(flow(p0), axis=1)
    dt = 0.25 * 2 * math.pi * 1e-3 / v[0]                 # a quarter turn of the first one
    p1 = advect(flow, p0, dt, steps=32)
    r0, r1 = np.hypot(p0[:, 0], p0[:, 1]), np.hypot(p1[:, 0], p1[:, 1])
    assert np.allclose(r1, r0, rtol=1e-7)
    assert p1[0] == pytest.approx([0, 1e-3, 0], abs=1e-9)  # quarter turn, counter-clockwise
    assert np.allclose(advect(Uniform((0.1, 0, -0.2)), p0, 0.01) - p0, [1e-3, 0, -2e-3])


def test_seeding_counts_and_box(small_camera, rng):
    box = SeedingBox.field_of_view(small_camera, (-5e-3, 5e-3))
    assert particle_count(small_camera, box, per_lenslet=0.2) == round(0.2 * 41 * 61)
    mm3 = box.volume * 1e9
    assert particle_count(small_camera, box, per_mm3=2.0) == round(2.0 * mm3)
    pts = random_particles(box, 500, rng)
    assert pts.shape == (500, 3)
    assert (pts[:, 2] >= -5e-3).all() and (pts[:, 2] <= 5e-3).all()
    with pytest.raises(ConfigError, match="exactly one"):
        particle_count(small_camera, box)
    with pytest.raises(ConfigError, match="lo < hi"):
        SeedingBox((0, 1), (1, 0), (0, 1))
    with pytest.raises(ConfigError, match="core_radius"):
        LambOseen(core_radius=0.0)
