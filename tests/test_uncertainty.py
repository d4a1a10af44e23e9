"""plenopiv.piv.uncertainty: the chain's measured response and how it completes the correlation
statistics (the whole-chain coverage is in test_vortex_validation.py and
docs/validation/uncertainty.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plenopiv.piv import VectorField
from plenopiv.piv.uncertainty import MIN_GAIN, Response, cached_response, combine, response_key


def _response(gain_w=0.5, random_w=2e-5):
    z = np.array([-1e-3, 0.0, 1e-3])
    shifts = np.array([[1e-4, 1e-4, 5e-5], [2e-4, 2e-4, 1e-4]])
    gain = np.ones((2, 3, 3))
    gain[:, 2, :] = gain_w
    random = np.zeros((2, 3, 3))
    random[:, 2, :] = random_w
    return Response(z, shifts, gain, random, 100)


def _field(w=1e-4, sigma=1e-5):
    shape = (3, 2, 2)
    ones = np.ones(shape)
    return VectorField(x=np.arange(2) * 1e-3, y=np.arange(2) * 1e-3,
                       z=np.array([-1e-3, 0.0, 1e-3]), u=ones * 2e-4, v=ones * 0.0,
                       w=ones * w, valid=np.ones(shape, bool), snr=ones * 3,
                       correlation=ones * 0.8, u_uncertainty=ones * sigma,
                       v_uncertainty=ones * sigma, w_uncertainty=ones * sigma)


def test_combine_adds_the_response_in_quadrature():
    f = combine(_field(w=1e-4, sigma=1e-5), _response(gain_w=0.5, random_w=2e-5))
    # w measured with gain 0.5: its true value is twice it, the error as large as the value
    expected = np.sqrt(1e-5**2 + 2e-5**2 + 1e-4**2)
    np.testing.assert_allclose(f.w_uncertainty, expected)
    # gain 1 and no random error: u and v keep the correlation statistics
    np.testing.assert_allclose(f.u_uncertainty, 1e-5)
    np.testing.assert_allclose(f.v_uncertainty, 1e-5)
    assert set(f.uncertainty_parts) >= {"response_random", "response_gain"}
    assert combine(_field(), None).w_uncertainty[0, 0, 0] == 1e-5


def test_a_vector_the_chain_barely_sees_is_bounded():
    f = combine(_field(w=1e-4, sigma=0.0), _response(gain_w=0.0, random_w=0.0))
    np.testing.assert_allclose(f.w_uncertainty, (1 - MIN_GAIN) / MIN_GAIN * 1e-4)


def test_response_interpolates_between_layers():
    r = _response()
    r = Response(r.z, r.shifts, r.gain.copy(), r.random, 100)
    r.gain[:, 2, :] = [0.2, 0.6, 1.0]
    gain, _ = r.at([-0.5e-3, 0.5e-3, 2e-3])
    np.testing.assert_allclose(gain[2], [0.4, 0.8, 1.0])


def test_response_cache_round_trip_and_key(tmp_path):
    path = tmp_path / "response.json"
    calls = []

    def compute():
        calls.append(1)
        return _response()

    key = response_key("weights", [1, 2], {"a": 1})
    first, cached = cached_response(path, key, compute)
    assert not cached and path.exists()
    again, cached = cached_response(path, key, compute)
    assert cached and len(calls) == 1
    np.testing.assert_array_equal(again.gain, first.gain)
    _, cached = cached_response(path, response_key("another grid"), compute)
    assert not cached and len(calls) == 2
    path.write_text("{broken")
    _, cached = cached_response(path, key, compute)
    assert not cached and json.loads(path.read_text())["key"] == key
    assert cached_response(None, key, lambda: None) == (None, False)


@pytest.mark.parametrize("bad", [{"version": 0}, {}])
def test_response_from_another_version_is_rejected(bad):
    with pytest.raises(ValueError, match="version"):
        Response.from_dict(bad)
