"""The real-recording study on a tiny camera: preprocessing restores the ideal chain's accuracy.

A 19 × 27-lenslet patch of the demo's camera, the exact calibration (a patch this small gives
the focal-point fit too little leverage), the ideal case against the black level with its
fixed pattern on a 12-bit ADC (:mod:`pipelines.studies.realcam`).
"""

from __future__ import annotations

import numpy as np
import pytest

from pipelines.studies.realcam import IDEAL, StudyCase, run_case, truth

pytestmark = pytest.mark.study

EFFECT = "black level + fixed pattern"


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    # 0.3 per lenslet: at 0.15 an 8-voxel window on this patch holds about one particle,
    # fewer than the two a vector needs ([piv] min_particles_per_window)
    setup = StudyCase(lenslets=(19, 27), windows=((8, 8, 8), (8, 8, 8)), calibrate=False,
                      particles_per_lenslet=0.3, rays_per_particle=1024)
    t = truth(setup)
    work = tmp_path_factory.mktemp("realcam")
    return {name: run_case(setup, name, t, work / str(k))
            for k, name in enumerate((IDEAL, EFFECT))}


def test_the_preprocessed_real_recording_is_as_accurate_as_the_ideal(cases):
    ideal, real = cases[IDEAL]["raw"], cases[EFFECT]["preprocessed"]
    assert real["n_vectors"] > 20
    rms_ideal, rms_real = np.asarray(ideal["rms_vox"]), np.asarray(real["rms_vox"])
    assert np.all(rms_real <= 1.5 * rms_ideal), (rms_real, rms_ideal)
    assert not real["warned"], real["warnings"]


def test_the_raw_real_recording_warns_and_names_the_dark(cases):
    ideal, raw = cases[IDEAL]["raw"], cases[EFFECT]["raw"]
    assert not ideal["warned"], ideal["warnings"]
    assert raw["warned"]
    assert "black level" in raw["warnings"][0]
    assert '[preprocess] dark = "DARK.tif"' in raw["warnings"][0]
