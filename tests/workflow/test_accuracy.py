"""Tests of plenopiv.workflow.accuracy.gain_bias_rms: slope, bias and rms of measured against
true displacements, on synthetic arrays with a known answer."""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.workflow.accuracy import gain_bias_rms


def test_known_gain_offset_and_noise(rng):
    true = rng.normal(0.0, 1.5, size=(3, 4, 5, 6))
    noise = rng.normal(0.0, 0.1, size=true.shape)
    gains = np.array([1.0, 0.5, 0.34])[:, None, None, None]
    offsets = np.array([0.0, 0.2, -0.1])[:, None, None, None]
    measured = gains * true + offsets + noise

    r = gain_bias_rms(measured, true)

    assert r["n"] == 4 * 5 * 6
    np.testing.assert_allclose(r["gain"], gains.ravel(), atol=0.03)
    np.testing.assert_allclose(r["offset"], offsets.ravel(), atol=0.03)
    err = measured - true
    np.testing.assert_allclose(r["bias"], err.reshape(3, -1).mean(axis=1), rtol=1e-12)
    np.testing.assert_allclose(r["rms"], np.sqrt((err**2).reshape(3, -1).mean(axis=1)),
                               rtol=1e-12)
    np.testing.assert_allclose(r["true_rms"], np.sqrt((true**2).reshape(3, -1).mean(axis=1)),
                               rtol=1e-12)
    assert r["correlation"][0] > 0.99
    # the standard error of the slope: noise / (spread of t * sqrt(n)) for independent samples
    np.testing.assert_allclose(r["gain_se"], 0.1 / (1.5 * np.sqrt(120)), rtol=0.25)


def test_an_antisymmetric_flow_at_a_third_of_its_size_has_no_bias_but_gain_one_third():
    # the case that motivated the gain: a bias near zero hides a flattened component
    x = np.linspace(-1.0, 1.0, 41)
    true = np.stack([2.0 * x, np.zeros_like(x), np.sin(np.pi * x)])
    measured = true / 3.0
    r = gain_bias_rms(measured, true)
    assert r["gain"][0] == pytest.approx(1 / 3)
    assert r["gain"][2] == pytest.approx(1 / 3)
    assert abs(r["bias"][2]) < 1e-12
    assert np.isnan(r["gain"][1]) and np.isnan(r["correlation"][1])   # v does not vary


def test_mask_and_non_finite_samples_are_left_out():
    true = np.array([[0.0, 1.0, 2.0, 3.0, 4.0]])
    measured = 2.0 * true
    measured[0, 4] = 100.0                      # an outlier, masked
    measured[0, 0] = np.nan                     # not finite: dropped
    r = gain_bias_rms(measured, true, mask=[True, True, True, True, False])
    assert r["n"] == 3
    assert r["gain"][0] == pytest.approx(2.0)
    assert r["bias"][0] == pytest.approx(2.0)


def test_uniform_shift_has_a_bias_and_no_gain():
    true = np.full((1, 10), 1.5)
    r = gain_bias_rms(true - 0.05, true)
    assert np.isnan(r["gain"][0]) and np.isnan(r["offset"][0])
    assert r["bias"][0] == pytest.approx(-0.05)
    assert r["rms"][0] == pytest.approx(0.05)


def test_empty_selection_and_bad_shapes():
    r = gain_bias_rms(np.zeros((3, 4)), np.zeros((3, 4)), mask=np.zeros(4, bool))
    assert r["n"] == 0 and all(np.isnan(r[k]).all() for k in ("gain", "bias", "rms"))
    with pytest.raises(ValueError, match="shape"):
        gain_bias_rms(np.zeros((3, 4)), np.zeros((3, 5)))
    with pytest.raises(ValueError, match="mask"):
        gain_bias_rms(np.zeros((3, 4)), np.zeros((3, 4)), mask=np.ones(5, bool))
