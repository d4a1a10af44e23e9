"""The ray-traced simulator: kernels against their NumPy twins, and the physics of each image."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plenopiv.camera import optics as O
from plenopiv.camera.model import ExternalInterface, Substrate
from plenopiv.conventions import sensor_to_pixel
from plenopiv.errors import ConfigError
from plenopiv.synthetic import _kernels as K
from plenopiv.synthetic.images import (
    Ruler,
    alignment_image,
    finish_image,
    focal_point_image,
    particle_image,
    ruler_image,
)
from plenopiv.synthetic.tracer import cell_points, geometry_vector, symmetric_disc_points

PLATES = {"none": None, "6.3mm n1.46": Substrate(6.3e-3, 1.46),
          "10.4mm n1.517": Substrate(10.4e-3, 1.517)}


def variant(camera, *, plate=None, back_side="physical", grid="square", offset=(0.0, 0.0),
            rotation=0.0, image_distance=None):
    mla = dataclasses.replace(camera.microlens_array, substrate=plate, back_side=back_side,
                              grid=grid, offset=offset, rotation=rotation)
    cam = camera.replace(microlens_array=mla)
    return cam if image_distance is None else cam.with_image_distance(image_distance)


def spot_centroids(image, predicted_rc, half=5):
    """Intensity-weighted centroids in (2 half + 1)² windows around predicted (row, col).

    Spots whose window leaves the sensor are returned as NaN.
    """
    rc = np.rint(predicted_rc).astype(int)
    ok = ((rc[:, 0] >= half) & (rc[:, 1] >= half) & (rc[:, 0] < image.shape[0] - half)
          & (rc[:, 1] < image.shape[1] - half))
    off = np.arange(-half, half + 1)
    rows = rc[ok, 0, None, None] + off[None, :, None]
    cols = rc[ok, 1, None, None] + off[None, None, :]
    win = image[rows, cols]
    total = win.sum(axis=(1, 2))
    out = np.full(predicted_rc.shape, np.nan)
    out[ok, 0] = (win * rows).sum(axis=(1, 2)) / total
    out[ok, 1] = (win * cols).sum(axis=(1, 2)) / total
    return out


def predicted_spots(cam):
    mla = cam.microlens_array
    p = O.focal_spot_exact(mla.centres(), cam.image_distance, mla.sensor_distance,
                           back_side=mla.back_side, thickness=cam.plate_thickness,
                           refractive_index=cam.plate_index,
                           pupil_offset=cam.main_lens.exit_pupil_offset)
    return sensor_to_pixel(p, cam.sensor.shape, cam.sensor.pixel_pitch)


# ---- kernels against their NumPy twins -----------------------------------------------------

@pytest.mark.parametrize("grid", ["square", "hexagonal"])
@pytest.mark.parametrize("plate", ["none", "10.4mm n1.517"])
@pytest.mark.parametrize("back_side", ["physical", "thesis"])
def test_trace_kernel_matches_numpy_twin(small_camera, rng, grid, plate, back_side):
    cam = variant(small_camera, plate=PLATES[plate], back_side=back_side, grid=grid,
                  offset=(17e-6, -9e-6), rotation=0.004)
    g = geometry_vector(cam)
    n = 4000
    r = 0.02 * np.sqrt(rng.random(n))
    phi = 2 * np.pi * rng.random(n)
    x0, y0 = r * np.cos(phi), r * np.sin(phi)
    w, h = cam.microlens_array.extent
    tx = rng.uniform(-0.55 * w, 0.55 * w, n)
    ty = rng.uniform(-0.55 * h, 0.55 * h, n)
    mx, my = (tx - x0) / cam.mla_z, (ty - y0) / cam.mla_z
    z0 = np.zeros(n)
    k1, sx1, sy1 = K.trace_image_rays(x0, y0, z0, mx, my, g)
    k2, sx2, sy2 = K.trace_image_rays_numpy(x0, y0, z0, mx, my, g)
    assert (k1 == k2).mean() > 0.999          # ties on cell borders are measure-zero
    same = (k1 == k2) & (k1 >= 0)
    assert same.sum() > 0.5 * n
    assert np.allclose(sx1[same], sx2[same], rtol=0, atol=1e-12)
    assert np.allclose(sy1[same], sy2[same], rtol=0, atol=1e-12)


@pytest.mark.parametrize("splat, shift", [("bilinear", (0.0, 0.0)), ("pixel", (0.0, 0.0)),
                                          ("bilinear", (0.3, -0.45)), ("pixel", (-0.2, 0.7))])
def test_splat_kernel_matches_numpy_twin(small_camera, rng, splat, shift):
    g = geometry_vector(small_camera, splat=splat, sensor_shift_px=shift)
    shape = small_camera.sensor.shape
    sx = rng.uniform(-1.1, 1.1, 500) * small_camera.sensor.width / 2
    sy = rng.uniform(-1.1, 1.1, 500) * small_camera.sensor.height / 2
    w = rng.random(500)
    img = np.zeros(shape)
    for a, b, c in zip(sx, sy, w, strict=True):
        K.splat(img, a, b, c, g)
    assert np.allclose(img, K.splat_numpy(np.zeros(shape), sx, sy, w, g), atol=1e-14)


def test_splat_preserves_energy_and_first_moment(small_camera):
    g = geometry_vector(small_camera)
    img = np.zeros(small_camera.sensor.shape)
    K.splat(img, 3.3e-6, -1.7e-6, 2.0, g)
    rr, cc = np.indices(img.shape)
    assert img.sum() == pytest.approx(2.0)
    expect = sensor_to_pixel([3.3e-6, -1.7e-6], img.shape, small_camera.sensor.pixel_pitch)
    assert (img * rr).sum() / 2 == pytest.approx(expect[0])
    assert (img * cc).sum() / 2 == pytest.approx(expect[1])


@pytest.mark.parametrize("choice", [dict(), dict(psf_px=0.6), dict(splat="pixel"),
                                    dict(splat="pixel", psf_px=0.6),
                                    dict(sensor_shift_px=(0.31, -0.27)),
                                    dict(splat="pixel", psf_px=0.6, sensor_shift_px=(-0.4, 0.2))])
def test_rendering_choices_keep_energy_and_move_by_the_sensor_shift(small_camera, choice):
    """Every choice keeps the light; a bilinear splat or a PSF-blurred pixel sensor keeps the
    image's first moment (the mean of the rays), shifted by exactly the sensor shift."""
    ref = focal_point_image(small_camera, f_number=16)
    img = focal_point_image(small_camera, f_number=16, **choice)
    assert img.shape == ref.shape and img.sum() == pytest.approx(ref.sum(), rel=1e-12)
    rr, cc = np.indices(img.shape)

    def moment(a):
        return np.array([(a * rr).sum(), (a * cc).sum()]) / a.sum()

    shift = np.asarray(choice.get("sensor_shift_px", (0.0, 0.0)))
    tol = 1e-2 if choice.get("splat") == "pixel" and not choice.get("psf_px") else 1e-9
    assert np.allclose(moment(img) - moment(ref), shift, atol=tol)
    if choice.get("splat") == "pixel" and not choice.get("psf_px"):
        assert np.count_nonzero(img) < np.count_nonzero(ref)   # whole rays, no sharing


def test_rendering_options_are_checked(small_camera):
    with pytest.raises(ConfigError, match="splat = 'nearest'"):
        focal_point_image(small_camera, f_number=16, splat="nearest")
    with pytest.raises(ConfigError, match="psf_px = -0.5"):
        alignment_image(small_camera, psf_px=-0.5)
    with pytest.raises(ConfigError, match="sensor_shift_px"):
        focal_point_image(small_camera, f_number=16, sensor_shift_px=(0.1,))


def test_object_ray_kernel_matches_numpy_twin(small_camera, rng):
    cam = small_camera.replace(external_interface=ExternalInterface(1.33, 1.0, 0.04))
    g = geometry_vector(cam)
    n = 300
    src = cam.volume_to_camera(np.c_[rng.uniform(-5e-3, 5e-3, (n, 2)),
                                     rng.uniform(-10e-3, 10e-3, n)])
    lens = rng.uniform(-0.02, 0.02, (n, 2))
    assert np.allclose(K.object_rays_to_lens(src, lens, g),
                       K.object_rays_to_lens_numpy(src, lens, g), rtol=1e-12, atol=1e-15)


def test_radial_solve_kernel_matches_twin_and_snell():
    for rho in (0.0, 1e-4, 0.01, 0.03):
        m = K.radial_solve(rho, 0.19, 0.0104, 1.517)
        assert m == pytest.approx(float(K.radial_solve_numpy(rho, 0.19, 0.0104, 1.517)), rel=1e-13,
                                  abs=1e-18)


def test_sampling_sets_are_symmetric(small_camera):
    disc = symmetric_disc_points(1.0, 15)
    assert np.allclose(disc.mean(axis=0), 0, atol=1e-15)
    assert np.all(np.hypot(*disc.T) <= 1 + 1e-12)
    hexcam = variant(small_camera, grid="hexagonal")
    for cam in (small_camera, hexcam):
        cells = cell_points(cam, 6)
        assert np.allclose(cells.mean(axis=0), 0, atol=1e-18)


# ---- image physics ----------------------------------------------------------------------------

CASES = [(si, plate, bs) for si in (0.145, 0.2, 0.27, 0.405) for plate in PLATES
         for bs in ("physical", "thesis") if not (plate == "none" and bs == "thesis")]


@pytest.mark.parametrize("si, plate, back_side", CASES)
def test_focal_spots_follow_the_exact_chief_ray_full_camera(auburn_camera, si, plate,
                                                            back_side):
    """Every lenslet of the full Auburn camera (135 mm lens, f/16): ≤ 0.01 px."""
    cam = variant(auburn_camera, plate=PLATES[plate], back_side=back_side, image_distance=si)
    img = focal_point_image(cam, f_number=16, pupil_across=7, cell_across=1)
    pred = predicted_spots(cam)
    got = spot_centroids(img, pred)
    inside = np.isfinite(got[:, 0])
    assert inside.sum() >= 0.98 * cam.microlens_array.count
    err = np.abs(got[inside] - pred[inside])
    assert err.max() <= 0.01, f"max centroid error {err.max():.2e} px"


@pytest.mark.parametrize("grid", ["square", "hexagonal"])
@pytest.mark.parametrize("plate, back_side", [("none", "physical"),
                                              ("10.4mm n1.517", "physical"),
                                              ("6.3mm n1.46", "thesis")])
def test_focal_spots_with_rotated_offset_array(small_camera, grid, plate, back_side):
    cam = variant(small_camera, plate=PLATES[plate], back_side=back_side, grid=grid,
                  offset=(23e-6, -31e-6), rotation=0.012, image_distance=0.145)
    img = focal_point_image(cam, f_number=16)
    pred = predicted_spots(cam)
    got = spot_centroids(img, pred)
    inside = np.isfinite(got[:, 0])
    assert inside.mean() > 0.9
    assert np.abs(got[inside] - pred[inside]).max() <= 0.01


def test_focal_spots_start_at_the_exit_pupil(small_camera):
    """With an exit-pupil offset e the spots scale as 1 + f̄/(S_i - e), not 1 + f̄/S_i."""
    lens = dataclasses.replace(small_camera.main_lens, exit_pupil_offset=0.03)
    cam = small_camera.replace(main_lens=lens)
    img = focal_point_image(cam, f_number=16)
    pred = predicted_spots(cam)
    got = spot_centroids(img, pred)
    ok = np.isfinite(got[:, 0])
    assert np.abs(got[ok] - pred[ok]).max() <= 0.01
    thin = sensor_to_pixel(cam.microlens_array.centres() * (1 + 500e-6 / 0.2),
                           cam.sensor.shape, cam.sensor.pixel_pitch)
    # the edge lenslets (3.8 mm off axis) move by d·f̄·(1/(S_i - e) - 1/S_i) = 0.22 px
    shift = np.abs(got[ok] - thin[ok]).max() * cam.sensor.pixel_pitch
    assert shift == pytest.approx(3.8125e-3 * 500e-6 * (1 / 0.17 - 1 / 0.2), rel=0.02)


@pytest.mark.parametrize("grid", ["square", "hexagonal"])
@pytest.mark.parametrize("plate", ["none", "10.4mm n1.517"])
def test_alignment_spots_lie_under_lenslet_centres(small_camera, grid, plate):
    cam = variant(small_camera, plate=PLATES[plate], grid=grid, offset=(11e-6, 5e-6),
                  rotation=-0.008)
    img = alignment_image(cam)
    c = sensor_to_pixel(cam.microlens_array.centres(), cam.sensor.shape,
                        cam.sensor.pixel_pitch)
    got = spot_centroids(img, c, half=3)
    ok = np.isfinite(got[:, 0])
    assert np.abs(got[ok] - c[ok]).max() <= 0.01


def test_in_focus_axis_point_lands_under_the_central_lenslet(small_camera):
    img = particle_image(small_camera, [[0.0, 0.0, 0.0]], rays_per_particle=10000)
    assert img.sum() == pytest.approx(1.0, rel=1e-9)        # every ray reaches the sensor
    centre = (np.array(img.shape) - 1) / 2
    half = small_camera.pitch_px / 2
    rr, cc = np.indices(img.shape)
    under = (np.abs(rr - centre[0]) <= half) & (np.abs(cc - centre[1]) <= half)
    assert img[under].sum() / img.sum() >= 0.9


def test_defocused_point_spreads_over_lenslets_in_proportion_to_depth(small_camera):
    """The blur disc on the lenslet plane grows as |ΔS_i|·D/S_i' (similar triangles)."""
    img = particle_image(small_camera, [[0.0, 0.0, -8e-3]], rays_per_particle=20000)
    cam = small_camera
    so = cam.object_distance - 8e-3
    si = 1 / (1 / cam.main_lens.focal_length - 1 / so)
    blur_diameter = cam.main_lens.aperture_diameter * (si - cam.image_distance) / si
    lit = np.argwhere(img > 1e-4 * img.max())
    extent = np.ptp(lit[:, 1]) * cam.sensor.pixel_pitch
    # the lit micro-images cover the blur disc plus at most one lenslet of partial coverage
    assert blur_diameter - cam.microlens_array.pitch < extent
    assert extent < blur_diameter + 2.5 * cam.microlens_array.pitch


def test_external_interface_scales_apparent_depth_by_n2_over_n1(small_camera):
    """Near-axis point in water (n1 = 1.33): ΔS_eff = (n2/n1) Δz within 1 % (Eq. 4.7)."""
    cam = small_camera.replace(external_interface=ExternalInterface(1.33, 1.0, 0.04))
    g = geometry_vector(cam, f_number=16)
    f = cam.main_lens.focal_length
    lens = symmetric_disc_points(g[K.G_RPUPIL], 21)
    for depth in (-10e-3, -4e-3, 4e-3, 10e-3):
        src = np.repeat(cam.volume_to_camera([[1e-4, 0.0, depth]]), len(lens), axis=0)
        m = K.object_rays_to_lens(src, lens, g) - lens / f        # after the thin lens
        # least-squares meeting point of the image-space rays x(z) = L + m z
        a = np.einsum("ij,ij->", m, m) - (m.sum(0) ** 2).sum() / len(m)
        b = np.einsum("ij,ij->", lens, m) - (lens.sum(0) * m.sum(0)).sum() / len(m)
        z_image = -b / a
        apparent = 1 / (1 / f - 1 / z_image) - cam.object_distance
        assert apparent / depth == pytest.approx(1 / 1.33, rel=0.01)


def test_ruler_ticks_darken_lenslets_at_the_tick_spacing(small_camera):
    """In focus, tick k lands on the lenslets at x = M·k·spacing (one lenslet = one sample)."""
    cam = small_camera
    img = ruler_image(cam, Ruler(spacing=1e-3, tick_width=0.2e-3), rays_per_lenslet=1500)
    mla = cam.microlens_array
    # integral image of the central lenslet row: sum each lenslet's pixel block
    pitch_px = cam.pitch_px * (1 + mla.sensor_distance / cam.image_distance)
    centre = (np.array(img.shape) - 1) / 2
    edges = centre[1] + (np.arange(mla.cols + 1) - mla.cols / 2) * pitch_px
    row_band = img[int(centre[0] - pitch_px / 2):int(centre[0] + pitch_px / 2)].sum(axis=0)
    per_lenslet = np.add.reduceat(row_band, np.round(edges[:-1]).astype(int))
    darkness = 1 - per_lenslet / np.median(per_lenslet)
    x_lenslet = (np.arange(mla.cols) - (mla.cols - 1) / 2) * mla.pitch     # metres, MLA plane
    ticks = []
    for k in range(1, mla.cols - 1):
        if darkness[k] > 0.15 and darkness[k] >= darkness[k - 1] and darkness[k] > darkness[k + 1]:
            w = np.clip(darkness[k - 1:k + 2], 0, None)
            ticks.append((w * x_lenslet[k - 1:k + 2]).sum() / w.sum())
    ticks = np.array(ticks)
    assert len(ticks) >= 10
    slope = np.polyfit(np.arange(len(ticks)), ticks, 1)[0]
    # image-side tick spacing |M| · 1 mm, to within the sub-lenslet sampling of a centroid
    assert slope == pytest.approx(abs(cam.magnification) * 1e-3, rel=0.02)


def test_particle_render_is_deterministic_and_batch_independent(small_camera, rng):
    pts = np.c_[rng.uniform(-2e-3, 2e-3, (40, 2)), rng.uniform(-4e-3, 4e-3, 40)]
    a = particle_image(small_camera, pts, rays_per_particle=512, seed=7)
    b = particle_image(small_camera, pts, rays_per_particle=512, seed=7)
    assert np.array_equal(a, b)
    from plenopiv.synthetic.tracer import render_sources

    src = small_camera.volume_to_camera(pts)
    c = render_sources(small_camera, src, np.ones(40), samples=512, seed=7, n_batches=5)
    assert np.allclose(a, c, rtol=1e-12, atol=1e-15)


def test_finish_image_noise_and_quantisation(rng):
    irr = np.zeros((50, 60))
    irr[20:30, 20:30] = 1.0
    img = finish_image(irr, bit_depth=16)
    assert img.dtype == np.uint16 and img.max() == round(0.8 * 65535)
    noisy = finish_image(irr, bit_depth=16, noise="poisson", full_well=10000, rng=rng)
    lit = noisy[20:30, 20:30].astype(float)
    # photon noise: σ/mean = 1/sqrt(electrons) = 1/sqrt(0.8 · 10000)
    assert lit.std() / lit.mean() == pytest.approx(1 / np.sqrt(8000), rel=0.35)
    with pytest.raises(ValueError, match="noise"):
        finish_image(irr, noise="gauss")


def test_stratified_aperture_sampling_beats_monte_carlo_noise(small_camera):
    """Centroid scatter over seeds is far below the σ/√N of independent random rays."""
    n = 1024
    centroids = []
    for seed in range(8):
        img = particle_image(small_camera, [[0.0, 0.0, 0.0]], rays_per_particle=n, seed=seed)
        rr, cc = np.indices(img.shape)
        centroids.append([(img * rr).sum() / img.sum(), (img * cc).sum() / img.sum()])
    scatter = np.std(centroids, axis=0, ddof=1)
    # the micro-image is a uniform disc of radius R = f̄ D / (2 S_i); per-axis σ = R/2
    radius_px = (500e-6 * small_camera.main_lens.aperture_diameter / (2 * 0.2)
                 / small_camera.sensor.pixel_pitch)
    monte_carlo = (radius_px / 2) / np.sqrt(n)
    assert scatter.max() < 0.25 * monte_carlo, (scatter, monte_carlo)
